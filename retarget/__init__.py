"""Retargeting: the character the phone puppet moves. ``retarget.skeleton`` holds the skeleton and clip
types, forward kinematics and the default humanoid; ``retarget.bvh`` reads and writes BVH files;
``retarget.clips`` generates the embedded default clip set (idle, walk, run, crouch idle, crouch walk,
get-up, mid-jump)."""

from retarget.bvh import CMU_SCALE, format_bvh, parse_bvh, read_bvh, write_bvh
from retarget.clips import CLIP_NAMES, default_clips
from retarget.skeleton import (
    HUMANOID_JOINTS,
    Clip,
    Skeleton,
    bezier_control,
    bezier_spine,
    humanoid,
)

__all__ = [
    "CLIP_NAMES",
    "CMU_SCALE",
    "HUMANOID_JOINTS",
    "Clip",
    "Skeleton",
    "bezier_control",
    "bezier_spine",
    "default_clips",
    "format_bvh",
    "humanoid",
    "parse_bvh",
    "read_bvh",
    "write_bvh",
]
