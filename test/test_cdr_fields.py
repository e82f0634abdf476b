"""packml_ros2.cdr_fields: a few fields read from the bytes give rclpy's decoded values, and bytes
that are not a plain CDR serialization of the type are refused."""

from __future__ import annotations

import random

import pytest
from packml_interfaces.msg import (
    Descriptor,
    EmSummary,
    Ingredient,
    Product,
    RemoteInterface,
    Status,
    TransitionEvent,
)
from rclpy.serialization import deserialize_message, serialize_message

from packml_ros2.cdr_fields import Unreadable, field_reader
from packml_ros2.equipment_module import status_view

HEAD = ["state_current", "sequence", "unit_mode_current", "unit_mode_requested",
        "unit_mode_change_in_process", "unit", "mach_speed"]  # fmt: skip
EMS = ["name", "active", "state_complete", "sequence", "stale_reports"]
read = field_reader(Status, HEAD, {"equipment_modules": EMS})


def text(rng: random.Random) -> str:
    return "".join(rng.choice("aZ_ 9éß€\U0001f916") for _ in range(rng.randrange(0, 12)))


def descriptors(rng: random.Random) -> list[Descriptor]:
    return [Descriptor(id=rng.randrange(-9, 9), name=text(rng), unit=text(rng), value=rng.random())
            for _ in range(rng.randrange(0, 3))]  # fmt: skip


def random_status(rng: random.Random) -> Status:
    """Every variable part of a Status, with lengths that move the alignment around."""
    return Status(
        unit=text(rng), unit_mode_current=rng.randrange(-5, 99), unit_mode_requested=rng.randrange(99),
        unit_mode_change_in_process=rng.random() < 0.5, state_current=rng.randrange(18),
        mach_speed=rng.uniform(-1e9, 1e9), material_interlock=rng.randrange(2**32),
        remote_interface=[RemoteInterface(number=rng.randrange(9), parameter=descriptors(rng))
                          for _ in range(rng.randrange(0, 3))],
        parameter=descriptors(rng),
        product=[Product(product_id=rng.randrange(9), process_variables=descriptors(rng),
                         ingredients=[Ingredient(parameter=descriptors(rng))
                                      for _ in range(rng.randrange(0, 3))])
                 for _ in range(rng.randrange(0, 3))],
        state_current_name=text(rng), unit_mode_current_name=text(rng),
        sequence=rng.randrange(2**32), commands_valid=[rng.randrange(10) for _ in range(rng.randrange(5))],
        commands_valid_names=[text(rng) for _ in range(rng.randrange(5))],
        equipment_modules=[EmSummary(name=text(rng), active=rng.random() < 0.5,
                                     state_complete=rng.random() < 0.5, sequence=rng.randrange(2**32),
                                     stale_reports=rng.randrange(2**32), blocked=rng.random() < 0.5)
                           for _ in range(rng.randrange(0, 10))],
        alarm_banner=text(rng),
    )  # fmt: skip


def expected(msg: Status) -> tuple[object, ...]:
    return (*(getattr(msg, f) for f in HEAD),
            [tuple(getattr(e, f) for f in EMS) for e in msg.equipment_modules])  # fmt: skip


def test_the_fields_read_are_rclpys_decoded_values() -> None:
    rng = random.Random(30050)
    for _ in range(400):
        raw = serialize_message(random_status(rng))
        assert read(raw) == expected(deserialize_message(raw, Status))


def test_a_cut_buffer_is_refused_or_read_right() -> None:
    """Cut anywhere: refused, or (cut after the last field it needs) read as the whole one."""
    rng = random.Random(7)
    raw = serialize_message(random_status(rng))
    whole = read(raw)
    refused = 0
    for end in range(len(raw)):
        try:
            assert read(raw[:end]) == whole
        except Unreadable:
            refused += 1
    assert refused > len(raw) // 2


def test_other_encodings_and_garbage_are_refused() -> None:
    raw = serialize_message(Status(unit="u", sequence=3))
    for bad in (b"", b"\x00", b"\x00\x07" + raw[2:], b"\x01\x00" + raw[2:],
                b"\x00\x01\x00\x00" + b"\xff" * 40):  # fmt: skip
        with pytest.raises(Unreadable):
            read(bad)


def test_a_huge_count_is_refused_without_looping_over_it() -> None:
    msg = Status(unit="u", equipment_modules=[EmSummary(name="a")])
    raw = bytearray(serialize_message(msg))
    small = field_reader(Status, [], {"equipment_modules": ["name"]})
    assert small(bytes(raw)) == ([("a",)],)
    at = raw.index(b"\x01\x00\x00\x00\x02\x00\x00\x00a\x00")  # the EM count, then its name
    raw[at : at + 4] = (2**31).to_bytes(4, "little")
    with pytest.raises(Unreadable):
        small(bytes(raw))


def test_fields_are_checked_when_the_reader_is_made() -> None:
    with pytest.raises(ValueError, match="no field"):
        field_reader(Status, ["state"])
    with pytest.raises(ValueError, match="not a sequence of messages"):
        field_reader(Status, [], {"commands_valid": []})
    with pytest.raises(ValueError, match="only primitives and strings"):
        field_reader(TransitionEvent, ["stamp"])


def test_an_em_finds_its_own_entry_and_refuses_what_is_no_status() -> None:
    msg = Status(state_current=3, sequence=12, unit_mode_current=1, equipment_modules=[
        EmSummary(name="gripper", active=True, state_complete=True),
        EmSummary(name="robot", active=False, state_complete=False)])  # fmt: skip
    raw = serialize_message(msg)
    assert status_view(raw, "robot").mine == (False, False)
    assert status_view(raw, "gripper").mine == (True, True)
    view = status_view(raw, "vision")
    assert (view.state, view.sequence, view.mode, view.mine) == (3, 12, 1, None)
    with pytest.raises(ValueError, match="not a status"):
        status_view(b"\x00\x01\x00\x00" + b"\xff" * 40, "robot")
