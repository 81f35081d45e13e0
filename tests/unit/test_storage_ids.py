"""Campaign and study ids are never read as numbers by a table reader."""

from __future__ import annotations

import re

from ra2vipas.services.orchestrator.storage import new_record_id


def test_ids_are_twelve_hex_digits_that_no_reader_takes_for_a_number():
    ids = {new_record_id() for _ in range(20_000)}
    assert len(ids) == 20_000
    assert all(re.fullmatch(r"[a-f][0-9a-f]{11}", i) for i in ids)
    for i in ids:  # pandas' and Python's number parsing: '700730860640' and '123e45678901' were both possible
        try:
            float(i)
        except ValueError:
            continue
        raise AssertionError(f"{i} reads as a number")
    assert {i[0] for i in ids} == set("abcdef")
