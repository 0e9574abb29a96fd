"""The EP7047 modulo cases from the manual (the project's own copy under tests/)."""

from __future__ import annotations

import csv
from decimal import Decimal
from typing import NamedTuple

from servotune.devices.ep7047.codec import StartType
from tests.support.paths import TESTS

# The project's copy of the manual's modulo tables (source named in the file's header):
# tests never read anything outside the repository.
CASES_CSV = TESTS / "device" / "ep7047" / "data" / "ep7047_modulo_cases.csv"


class ModuloCase(NamedTuple):
    start_type: StartType
    window: int
    start: int
    target: int
    relative: int
    abs_end: int
    mod_end: int


def counts(degrees: str) -> int:
    value = Decimal(degrees) * 10
    assert value == value.to_integral_value(), degrees
    return int(value)


def load_cases() -> list[ModuloCase]:
    with CASES_CSV.open(newline="") as file:
        rows = [line for line in file if not line.startswith("#")]
    return [
        ModuloCase(
            StartType[row["start_type"]],
            counts(row["window"]),
            counts(row["start"]),
            counts(row["target"]),
            counts(row["relative"]),
            counts(row["abs_end"]),
            counts(row["mod_end"]),
        )
        for row in csv.DictReader(rows)
    ]
