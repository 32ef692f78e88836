"""The gaitmap walk (``../shared/traces/a_imu_csv/gaitmap_walk``) for the cycle tests: the two foot IMUs with
their column names, and each foot's annotated strides. Tests skip, naming the path, where the traces are not
beside the project."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

TRACES = Path(__file__).resolve().parents[1].parent / "shared" / "traces"
GAIT_IMU = TRACES / "a_imu_csv" / "gaitmap_walk"
GAIT_MOCAP = TRACES / "d_mocap_cyclic" / "gaitmap_walk"
IMU_HZ = 204.8


def gait_imu() -> tuple[np.ndarray, np.ndarray, list[str], list[str]]:
    """``(t_s, data, sensor, axis)``: the IMU take (``data[:, 0]`` is the sample index) and, per column, its
    sensor (``left_sensor``/``right_sensor``) and axis (``acc_x`` ... ``gyr_z``)."""
    path = GAIT_IMU / "imu_sample_not_rotated.csv"
    if not path.exists():
        pytest.skip(f"gaitmap walk not found at {path} (../shared/traces must sit beside the project)")
    with path.open(newline="") as f:
        rows = csv.reader(f)
        sensor, axis = next(rows), next(rows)
    data = np.loadtxt(path, delimiter=",", skiprows=2)
    return data[:, 0] / IMU_HZ, data, sensor, axis


def gait_strides(foot: str) -> np.ndarray:
    """``(k, 2)`` start and end (s) of each annotated stride of ``foot``; the borders are sample indices at
    the IMU's 204.8 Hz in both folders."""
    with (GAIT_IMU / "stride_borders_sample.csv").open(newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["foot"] == foot]
    return np.array([[float(r["start"]), float(r["end"])] for r in rows]) / IMU_HZ
