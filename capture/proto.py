"""Protobuf schemas built in code, for sessions and live viewers: each one a self-describing
``FileDescriptorSet`` (the schema data MCAP and the Foxglove WebSocket protocol carry), so any protobuf
reader decodes perfcap's messages with no perfcap code and no ``.proto`` file.

This module owns the helpers every schema uses: a message declared as ``(name, type, label)`` fields,
its descriptor set with all its dependencies, and the message class to build and parse it with (the
``protobuf`` library's; nothing here encodes or parses the wire format itself).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

if TYPE_CHECKING:
    from collections.abc import Sequence

    from google.protobuf.descriptor import FileDescriptor

F = descriptor_pb2.FieldDescriptorProto
#: field types by the names ``.proto`` files use
TYPES = {"double": F.TYPE_DOUBLE, "float": F.TYPE_FLOAT, "sint64": F.TYPE_SINT64, "uint32": F.TYPE_UINT32,
         "uint64": F.TYPE_UINT64, "bytes": F.TYPE_BYTES, "string": F.TYPE_STRING, "message": F.TYPE_MESSAGE}


@dataclass(frozen=True, slots=True)
class Field:
    """One field of a message declared in code: ``repeated`` ones are packed (proto3's default)."""

    name: str
    type: str
    repeated: bool = False
    message: str = ""      # the full name of a message type (``type == "message"``)
    doc: str = ""


@dataclass(frozen=True, slots=True)
class ProtoSchema:
    """A message type with its self-describing schema: ``name`` (full name, what MCAP's schema record
    and Foxglove call the schema), ``data`` (a serialized ``FileDescriptorSet``), and ``cls`` to build
    and parse messages with."""

    name: str
    data: bytes
    cls: Any


def with_dependencies(files: Sequence[FileDescriptor]) -> list[FileDescriptor]:
    """``files`` and every file they depend on, each once, dependencies first."""
    out: list[FileDescriptor] = []
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        out.append(fd)

    for f in files:
        add(f)
    return out


def descriptor_set(file: FileDescriptor) -> bytes:
    """A ``FileDescriptorSet`` of ``file`` and every file it depends on, dependencies first."""
    out = descriptor_pb2.FileDescriptorSet()
    for fd in with_dependencies([file]):
        out.file.add().ParseFromString(fd.serialized_pb)
    return out.SerializeToString()


def schema_of(message_cls: Any) -> ProtoSchema:
    """The schema of a generated message class (Foxglove's well-known ones)."""
    d = message_cls.DESCRIPTOR
    return ProtoSchema(d.full_name, descriptor_set(d.file), message_cls)


def build(package: str, file_name: str, messages: Sequence[tuple[str, Sequence[Field], str]],
          deps: Sequence[FileDescriptor] = ()) -> dict[str, ProtoSchema]:
    """Declare messages ``(name, fields, doc)`` in one proto3 file; their schemas by short name.

    Field numbers follow the order given, from 1. The docs go into the file's source info, so a
    viewer that shows comments shows them.
    """
    fdp = descriptor_pb2.FileDescriptorProto(name=file_name, package=package, syntax="proto3")
    for d in deps:
        fdp.dependency.append(d.name)
    for mi, (mname, fields, mdoc) in enumerate(messages):
        m = fdp.message_type.add(name=mname)
        _doc(fdp, [4, mi], mdoc)
        for fi, f in enumerate(fields):
            # json_name spelled out as the name itself: the default (camel case) makes ``a_b`` and ``aB`` clash
            fp = m.field.add(name=f.name, number=fi + 1, type=TYPES[f.type], json_name=f.name,
                             label=F.LABEL_REPEATED if f.repeated else F.LABEL_OPTIONAL)
            if f.type == "message":
                fp.type_name = "." + f.message
            _doc(fdp, [4, mi, 2, fi], f.doc)
    pool = descriptor_pool.DescriptorPool()
    for fd in with_dependencies(deps):
        pool.Add(descriptor_pb2.FileDescriptorProto.FromString(fd.serialized_pb))
    pool.Add(fdp)
    data = descriptor_set(pool.FindFileByName(file_name))
    return {mname: ProtoSchema(f"{package}.{mname}", data,
                               message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{package}.{mname}")))
            for mname, _f, _d in messages}


def _doc(fdp: descriptor_pb2.FileDescriptorProto, path: list[int], text: str) -> None:
    if text:
        loc = fdp.source_code_info.location.add()
        loc.path.extend(path)
        loc.span.extend([0, 0, 0])
        loc.leading_comments = " " + text + "\n"


_IDENT = re.compile(r"[^A-Za-z0-9_]")


def identifier(name: str, taken: set[str] | None = None) -> str:
    """``name`` as a protobuf identifier (letters, digits, ``_``; not starting with a digit), made unique
    against ``taken`` (which it joins)."""
    ident = _IDENT.sub("_", name) or "_"
    if ident[0].isdigit():
        ident = "_" + ident
    if taken is not None:
        base, k = ident, 2
        while ident in taken:
            ident = f"{base}_{k}"
            k += 1
        taken.add(ident)
    return ident
