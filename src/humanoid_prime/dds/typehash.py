"""ROS 2's type hashes (RIHS01, REP 2011) of the message types Prime speaks, computed from their definitions.

A hash is the SHA-256 of a type description in JSON: the type's fields (name, field type id, capacities,
nested type name) and every type it refers to, sorted by name, with default values left out
(``rosidl_generator_type_description``). ROS 2 (Iron and later) puts it in each endpoint's user data as
``typehash=RIHS01_<hex>;``; without it, ROS tools list the topic's type hash as INVALID. The descriptions are
derived from the field lists in ``messages.py``, so the hash cannot drift from the bytes Prime sends; the
tests compare every hash with the one the ROS 2 wheels compute.
"""

from __future__ import annotations

import hashlib
import json
from functools import cache
from typing import get_args

from cyclonedds.idl import IdlStruct
from cyclonedds.idl._type_normalize import get_extended_type_hints
from cyclonedds.idl.types import array, bounded_str, sequence

# type_description_interfaces/msg/FieldType: the basic types' ids; nested kinds add an offset.
FIELD_TYPE_IDS = {
    "nested": 1, "int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8, "uint64": 9,
    "float32": 10, "float64": 11, "char": 13, "bool": 15, "byte": 16, "string": 17, "bounded_string": 21,
}
ARRAY, BOUNDED_SEQUENCE, UNBOUNDED_SEQUENCE = 48, 96, 144
Json = dict[str, object]  # a part of a type description, as it is hashed


def ros_type_name(cls: type[IdlStruct]) -> str:
    """``sensor_msgs::msg::dds_::JointState_`` -> ``sensor_msgs/msg/JointState``."""
    package, kind, _, name = cls.__idl_typename__.split("::")
    return f"{package}/{kind}/{name.removesuffix('_')}"


def _field_type(annotation: object) -> tuple[Json, type[IdlStruct] | None]:
    """The FieldType of one field annotation, and the nested struct it names (if any)."""
    offset, capacity, element = 0, 0, annotation
    if isinstance(annotation, array):
        offset, capacity, element = ARRAY, int(annotation.length), annotation.subtype
    elif isinstance(annotation, sequence):
        bound = annotation.max_length
        offset = UNBOUNDED_SEQUENCE if bound is None else BOUNDED_SEQUENCE
        capacity, element = (0 if bound is None else int(bound)), annotation.subtype
    nested: type[IdlStruct] | None = None
    string_capacity = 0
    if isinstance(element, type) and issubclass(element, IdlStruct):
        base, nested = "nested", element
    elif element is str:
        base = "string"
    elif isinstance(element, bounded_str):
        base, string_capacity = "bounded_string", element.max_length
    else:
        base = str(get_args(element)[1])  # cyclonedds' primitives: Annotated[int, 'int32']
    return ({"type_id": FIELD_TYPE_IDS[base] + offset, "capacity": capacity, "string_capacity": string_capacity,
             "nested_type_name": ros_type_name(nested) if nested is not None else ""}, nested)


def _individual(cls: type[IdlStruct]) -> tuple[Json, list[type[IdlStruct]]]:
    fields, nested = [], []
    for name, annotation in get_extended_type_hints(cls).items():
        field_type, inner = _field_type(annotation)
        fields.append({"name": name, "type": field_type})
        if inner is not None:
            nested.append(inner)
    return {"type_name": ros_type_name(cls), "fields": fields}, nested


def type_description(cls: type[IdlStruct]) -> Json:
    """The hashed form of ``cls``'s TypeDescription: the type and every type it refers to (defaults left out)."""
    top, pending = _individual(cls)
    referenced: dict[str, Json] = {}
    while pending:
        inner = pending.pop()
        name = ros_type_name(inner)
        if name not in referenced:
            referenced[name], more = _individual(inner)
            pending.extend(more)
    return {"type_description": top, "referenced_type_descriptions": [referenced[n] for n in sorted(referenced)]}


@cache
def type_hash(cls: type[IdlStruct]) -> str:
    """``RIHS01_<64 hex digits>`` of ``cls`` (JSON with ROS 2's separators, as rosidl hashes it)."""
    text = json.dumps(type_description(cls), ensure_ascii=True, separators=(", ", ": "))
    return "RIHS01_" + hashlib.sha256(text.encode()).hexdigest()


def user_data(cls: type[IdlStruct]) -> bytes:
    """An endpoint's user data as ROS 2 (Iron and later) writes it."""
    return f"typehash={type_hash(cls)};".encode()
