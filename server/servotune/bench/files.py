"""Export and import of bench runs: a JSON document (everything but the samples) and a
CSV file (the samples), checked completely on the way in, streamed on the way out.

Everything here is synchronous. An import of tens of megabytes parses for seconds of
pure Python, and it must never hold the event loop (a STOP must reach the wire
meanwhile): a worker *thread* is not enough, because it competes with the loop for
the interpreter (docs/bench.md has the figures). So the server writes the upload to a
temporary file and runs ``import_in_process`` in a separate process that opens the
database itself (WAL: the server keeps reading and writing meanwhile) and exits
afterwards, which also gives its memory back. The CSV is read row by row (never held
whole as Python objects) and stored in chunks of ``IMPORT_CHUNK_ROWS`` rows, so the
memory an import needs is its body plus one chunk. Exports read one stored chunk per
worker-thread call.

Validation is complete: the JSON is parsed by a pydantic model with strict types
(a number is a JSON number, not a string) and finite floats only (NaN, infinities and
overflowing numbers such as 1e400 are refused), the run must be finished (``complete``
or ``incomplete``), of the device of the axis it is imported onto, and the CSV must
have the JSON's columns, finite numbers, 0/1 flags and non-decreasing times. Every
refusal is an ``InvalidArgumentError`` naming the field (``meta.created_s``,
``csv``: with the line number) — a 422, and nothing is stored.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import re
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictInt, ValidationError

from servotune.bench.quality import SAMPLING_RULE, rejudge
from servotune.link.base import BenchKind, InvalidArgumentError
from servotune.schema import FiniteFloat, RunMetrics
from servotune.storage import Storage, StorageError, dumps_strict

MAX_IMPORT_BYTES = 64 * 1024 * 1024
"""Largest import body (multipart: the JSON and the CSV file together): 413 beyond."""
MAX_IMPORT_JSON_BYTES = 16 * 1024 * 1024
"""Largest import as one JSON body ``{"meta", "csv"}``. Smaller than the multipart
limit because a JSON document is parsed in one call that holds the interpreter
(about 10 ms per 4 MiB here, 2.5x that on a loaded host): bigger runs go as multipart."""
MAX_META_BYTES = 1024 * 1024
IMPORT_CHUNK_ROWS = 1000


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


class ImportIdentity(_Strict):
    link: str = ""
    path: str = ""
    address: StrictInt = 0
    name: str = ""


class ImportTest(_Strict):
    kind: BenchKind
    distance: StrictInt = 0
    velocity: StrictInt = 0
    pwm: StrictInt = 0
    duration_s: FiniteFloat = Field(default=0.0, ge=0)
    note: str = Field(default="", max_length=200)
    # frequency_response (servotune/bench/frf.py)
    amplitude: StrictInt | None = None
    low_hz: FiniteFloat | None = None
    high_hz: FiniteFloat | None = None
    model_based: StrictBool | None = None
    loop: Literal["closed", "open"] | None = None  # closed: ma targets; open: spwm


class ImportPlan(_Strict):
    response: str
    y0: FiniteFloat
    y_final: FiniteFloat
    band: FiniteFloat | None = Field(default=None, ge=0)
    overrides: dict[str, StrictInt] = Field(default_factory=dict)


class ImportReason(_Strict):
    code: str
    message: str


class ImportQuality(_Strict):
    status: Literal["good", "doubtful", "bad"]
    reasons: list[ImportReason]
    untrusted: dict[str, str] = Field(default_factory=dict)
    # the version of the sampling rule that judged it (runquality.SAMPLING_RULE)
    sampling_rule: StrictInt | None = None


class ImportReturn(_Strict):
    ok: StrictBool
    to: FiniteFloat
    error: FiniteFloat | None
    message: str = Field(max_length=500)


class RunExport(_Strict):
    """The JSON export of a run (``GET /api/bench/runs/{id}/run.json``), as imported."""

    id: str | None = None
    axis_id: str | None = None
    created_s: FiniteFloat = Field(ge=0, le=1e11, description="seconds since 1970")
    status: Literal["complete", "incomplete"] = Field(
        description="a finished run: a run still recording cannot be imported"
    )
    baseline: StrictBool = False
    axis_key: str = ""
    device: str
    model: str = ""
    identity: ImportIdentity = Field(default_factory=ImportIdentity)
    test: ImportTest
    params: dict[str, StrictInt]
    plan: ImportPlan
    columns: list[str] = Field(min_length=1, max_length=64)
    flags: list[str] = Field(max_length=64)
    metrics: RunMetrics | None  # the bench's own definition, strict and finite
    quality: ImportQuality | None = None
    message: str = Field(default="", max_length=2000)
    t0_s: FiniteFloat | None = None
    imported_from: str | None = None
    autotune: dict[str, Any] | None = None
    # frequency_response: the multisine and the targets sent; the model of a
    # model-based run; any run: when the device acknowledged the trigger.
    excitation: dict[str, Any] | None = None
    plant_model: dict[str, Any] | None = None
    trigger_latency_s: FiniteFloat | None = None
    # What the check after the run found: the axis left oscillating, or its loop not
    # verified (the run's quality names it too).
    left_oscillating: dict[str, Any] | None = None
    loop_unverified: dict[str, Any] | None = None
    return_: ImportReturn | None = Field(default=None, alias="return")


def _field_error(exc: ValidationError, prefix: str) -> InvalidArgumentError:
    first = exc.errors()[0]
    location = ".".join(str(p) for p in (prefix, *first.get("loc", ())))
    value = first.get("input")
    shown = repr(value) if not isinstance(value, dict | list) else type(value).__name__
    if len(shown) > 60:
        shown = shown[:57] + "..."
    return InvalidArgumentError(location, f"{location}: {first.get('msg')} (got {shown})")


def _check_finite(value: Any, where: str) -> None:
    """Refuse a non-finite number anywhere in free-form JSON (e.g. ``autotune``)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise InvalidArgumentError(where, f"{where}: numbers must be finite (got {value!r})")
    if isinstance(value, dict):
        for key, item in value.items():
            _check_finite(item, f"{where}.{key}")
    elif isinstance(value, list):
        for index, item in enumerate(value):
            _check_finite(item, f"{where}.{index}")


def validate_meta(raw: Any, device: str) -> RunExport:
    """The run's JSON checked completely for an axis of ``device`` (422 naming the field)."""
    if not isinstance(raw, dict):
        raise InvalidArgumentError("meta", "meta must be the run's JSON export (an object)")
    try:
        meta = RunExport.model_validate(raw)
    except ValidationError as exc:
        raise _field_error(exc, "meta") from None
    for name in ("autotune", "excitation", "plant_model"):
        if (value := getattr(meta, name)) is not None:
            _check_finite(value, f"meta.{name}")
    if meta.device != device:
        raise InvalidArgumentError(
            "meta.device", f"meta.device: this is a {meta.device} run, the axis is a {device}"
        )
    if meta.columns[0] != "t_s":
        raise InvalidArgumentError("meta.columns", "meta.columns must start with 't_s'")
    names = [*meta.columns, *meta.flags]
    if len(set(names)) != len(names):
        raise InvalidArgumentError("meta.columns", "meta.columns and meta.flags must be unique")
    if meta.plan.response not in meta.columns:
        raise InvalidArgumentError(
            "meta.plan.response", f"meta.plan.response {meta.plan.response!r} is not a column"
        )
    return meta


def _lines(text: str) -> Iterator[str]:
    """The lines of ``text`` one at a time (never a list of all of them)."""
    start, n = 0, len(text)
    while start < n:
        end = text.find("\n", start)
        if end < 0:
            yield text[start:]
            return
        yield text[start : end + 1]
        start = end + 1


def parse_csv(lines: Iterable[str], meta: RunExport) -> Iterator[list[list[Any]]]:
    """Sample rows of the CSV in chunks of ``IMPORT_CHUNK_ROWS`` (422 naming the line)."""
    reader = csv.reader(lines)
    try:
        header = next(reader, None)
    except (csv.Error, UnicodeDecodeError) as exc:
        raise InvalidArgumentError("csv", f"csv: line 1: {exc}") from None
    if header != [*meta.columns, *meta.flags]:
        raise InvalidArgumentError("csv", "csv: the header does not match meta.columns + flags")
    n_values, width = len(meta.columns), len(meta.columns) + len(meta.flags)
    chunk: list[list[Any]] = []
    previous_t = -math.inf
    line_no = 1
    try:
        for line_no, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != width:
                raise InvalidArgumentError(
                    "csv", f"csv: line {line_no}: {len(row)} fields, expected {width}"
                )
            values: list[Any] = []
            for name, text in zip(meta.columns, row[:n_values], strict=True):
                if text == "":
                    if name == "t_s":
                        raise InvalidArgumentError("csv", f"csv: line {line_no}: t_s is empty")
                    values.append(None)
                    continue
                try:
                    value = float(text)
                except ValueError:
                    raise InvalidArgumentError(
                        "csv", f"csv: line {line_no}: {name} {text[:20]!r} is not a number"
                    ) from None
                if not math.isfinite(value):
                    raise InvalidArgumentError(
                        "csv", f"csv: line {line_no}: {name} {text[:20]!r} is not finite"
                    )
                values.append(value)
            if values[0] < previous_t:
                raise InvalidArgumentError(
                    "csv", f"csv: line {line_no}: t_s {values[0]} is before the line above"
                )
            previous_t = values[0]
            flags = row[n_values:]
            if any(f not in ("0", "1") for f in flags):
                raise InvalidArgumentError("csv", f"csv: line {line_no}: flags must be 0 or 1")
            values.append([int(f) for f in flags])
            chunk.append(values)

            if len(chunk) >= IMPORT_CHUNK_ROWS:
                yield chunk
                chunk = []
    except (csv.Error, UnicodeDecodeError) as exc:
        raise InvalidArgumentError("csv", f"csv: line {line_no}: {exc}") from None
    if chunk:
        yield chunk


def store_import(
    storage: Storage,
    axis_key: str,
    axis_id: str,
    device: str,
    raw_meta: Any,
    csv_lines: Iterable[str],
    *,
    run_id: str,
) -> str:
    """Validate and store an imported run chunk by chunk as ``run_id``; returns it.

    On any refusal nothing stays stored (a partly written run is deleted). The caller
    chooses the id, so that it can delete what a process killed meanwhile left."""
    meta = validate_meta(raw_meta, device)
    stored = meta.model_dump(
        by_alias=True, exclude={"id", "axis_id", "status", "baseline", "created_s"}
    )
    stored["imported_from"] = meta.id or meta.imported_from
    for name in ("amplitude", "low_hz", "high_hz", "model_based", "loop"):
        if stored["test"].get(name) is None:
            stored["test"].pop(name, None)  # only frequency-response runs have them
    for optional in (
        "quality",
        "return",
        "autotune",
        "excitation",
        "plant_model",
        "trigger_latency_s",
        "left_oscillating",
        "loop_unverified",
    ):
        if stored.get(optional) is None:
            stored.pop(optional, None)
    storage.create_run(run_id, axis_key, axis_id, meta.created_s or time.time(), stored)
    # What the sampling rule reads, kept compact: (t, response, following error).
    judged = _JudgedColumns(meta.columns, meta.plan.response)
    try:
        for seq, chunk in enumerate(parse_csv(csv_lines, meta)):
            storage.append_samples(run_id, seq, chunk)
            judged.add(chunk)
        # An exported run is judged again by this version's sampling rule: the same
        # rule for every run on the page, wherever it was recorded.
        again = rejudge({**stored, "columns": judged.columns}, judged.rows)
        if again is not None:
            stored["metrics"], stored["quality"] = again
        storage.finish_run(run_id, meta.status, stored)
    except BaseException:
        # If the database refuses writes, the error that got us here is reported.
        with contextlib.suppress(StorageError):
            storage.delete_run(run_id)
        raise
    return run_id


class _JudgedColumns:
    """The columns of imported rows the sampling rule reads (``bench.quality.rejudge``)."""

    def __init__(self, columns: list[str], response: str) -> None:
        wanted = ["t_s", response, "following_error"]
        self._index = [columns.index(c) if c in columns else None for c in wanted]
        self.columns = [
            c if i is not None else f"-{c}" for c, i in zip(wanted, self._index, strict=True)
        ]
        self.rows: list[tuple[Any, ...]] = []

    def add(self, chunk: list[list[Any]]) -> None:
        index = self._index
        self.rows.extend(tuple(r[i] if i is not None else None for i in index) for r in chunk)


def import_json_body(
    storage: Storage, axis_key: str, axis_id: str, device: str, body: bytes, *, run_id: str
) -> str:
    """An import sent as one JSON document ``{"meta": {...}, "csv": "..."}``."""
    try:
        document = json.loads(body)
    except (ValueError, UnicodeDecodeError) as exc:
        raise InvalidArgumentError("body", f"body: not JSON ({exc})") from None
    if not isinstance(document, dict) or set(document) != {"meta", "csv"}:
        raise InvalidArgumentError("body", 'body must be {"meta": <run.json>, "csv": <text>}')
    if not isinstance(document["csv"], str):
        raise InvalidArgumentError("csv", "csv must be the CSV export as text")
    text: str = document.pop("csv")
    return store_import(
        storage, axis_key, axis_id, device, document["meta"], _lines(text), run_id=run_id
    )


def import_files(
    storage: Storage,
    axis_key: str,
    axis_id: str,
    device: str,
    meta_bytes: bytes,
    csv_file: IO[bytes],
    *,
    run_id: str,
) -> str:
    """An import sent as multipart: the ``meta`` JSON and the ``csv`` file (read lazily)."""
    if len(meta_bytes) > MAX_META_BYTES:
        raise InvalidArgumentError("meta", f"meta: larger than {MAX_META_BYTES} bytes")
    try:
        raw = json.loads(meta_bytes)
    except (ValueError, UnicodeDecodeError) as exc:
        raise InvalidArgumentError("meta", f"meta: not JSON ({exc})") from None
    csv_file.seek(0)
    text = io.TextIOWrapper(csv_file, encoding="utf-8", newline="")
    try:
        return store_import(storage, axis_key, axis_id, device, raw, text, run_id=run_id)
    finally:
        text.detach()  # the caller closes the upload


ImportOutcome = tuple[str, str, str]
"""("ok", run id, "") or ("invalid", field, message) or ("storage", "", message)."""


IMPORT_NICE = 10
"""Niceness of the import process (see ``import_in_process``): 10 gives it ~1/10 of the
CPU weight of a nice-0 process competing for the same core."""


def _lower_priority() -> None:
    # Absolute, not os.nice(): a pool process that ran an import before stays at 10.
    with contextlib.suppress(OSError, AttributeError):  # not on this OS: run as is
        current = os.getpriority(os.PRIO_PROCESS, 0)
        os.setpriority(os.PRIO_PROCESS, 0, max(current, IMPORT_NICE))


def import_in_process(
    db_path: str,
    axis_key: str,
    axis_id: str,
    device: str,
    body_path: str,
    meta_bytes: bytes | None,
    run_id: str,
) -> ImportOutcome:
    """Entry point of the import process: ``body_path`` holds the JSON body, or the
    CSV file when ``meta_bytes`` (multipart) is given; the run is stored as ``run_id``.
    Errors come back as values (exceptions with extra fields do not survive pickling).

    The process first lowers its own priority (``IMPORT_NICE``): on a 2-core host it
    otherwise takes a whole core from the server while the server's event loop and
    the EtherCAT cycle thread have work to do, and STOPs wait (docs/bench.md). At
    nice 10 the kernel gives the server the CPU whenever it is runnable; the import
    only takes longer."""
    _lower_priority()
    storage = Storage(Path(db_path))
    try:
        if storage.problem:
            return ("storage", "", f"not saved: {storage.problem}")
        with open(body_path, "rb") as body:
            if meta_bytes is None:
                import_json_body(storage, axis_key, axis_id, device, body.read(), run_id=run_id)
            else:
                import_files(storage, axis_key, axis_id, device, meta_bytes, body, run_id=run_id)
        return ("ok", run_id, "")
    except InvalidArgumentError as exc:
        return ("invalid", exc.field, str(exc))
    except StorageError as exc:
        return ("storage", "", str(exc))
    finally:
        storage.close()


def needs_rejudging(run: dict[str, Any]) -> bool:
    """A finished run with metrics that an older sampling rule judged."""
    quality = run.get("quality") or {}
    return (
        run.get("status") != "recording"
        and bool(run.get("metrics"))
        and quality.get("sampling_rule") != SAMPLING_RULE
    )


def rejudge_in_process(db_path: str) -> int:
    """Entry point of a process that judges every stored run that an older sampling
    rule judged (``bench.quality.rejudge``) and stores the new metrics and quality;
    returns how many changed. At the import's low priority, one run at a time."""
    _lower_priority()
    storage = Storage(Path(db_path))
    changed = 0
    try:
        if storage.problem:
            return 0
        for run_id in storage.run_ids():
            run = storage.get_run_meta(run_id)
            if run is None or not needs_rejudging(run):
                continue
            judged = _JudgedColumns(
                list(run.get("columns") or []), (run.get("plan") or {}).get("response", "")
            )
            for chunk in storage.iter_chunks(run_id):
                judged.add(chunk)
            again = rejudge({**run, "columns": judged.columns}, judged.rows)
            if again is None:
                continue
            meta = {
                k: v
                for k, v in run.items()
                if k not in ("id", "axis_id", "created_s", "status", "baseline")
            }
            meta["metrics"], meta["quality"] = again
            storage.finish_run(run_id, run["status"], meta)
            changed += 1
        return changed
    except StorageError:
        return changed
    finally:
        storage.close()


def csv_header(run: dict[str, Any]) -> str:
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerow([*run["columns"], *run["flags"]])
    return out.getvalue()


def csv_rows(rows: Iterable[list[Any]]) -> str:
    """Sample rows as CSV lines: values (empty for null), then one 0/1 per flag."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    for row in rows:
        values = ["" if v is None else repr(v) for v in row[:-1]]
        writer.writerow([*values, *row[-1]])
    return out.getvalue()


# Stored chunks are compact JSON written by ``json.dumps`` (``storage.dumps_strict``):
# numbers in ``repr`` form, ``null``, rows ``[v, ..., [flags]]``. Text made of these
# characters only is turned into CSV by a few ``str.replace`` calls (C speed, the same
# text as ``csv_rows``); anything else takes the general path.
_PLAIN_CHUNK = re.compile(r"[^0-9.,+\-e\[\]nul]")


def chunk_csv(storage: Storage, run_id: str, seq: int) -> str:
    """The rows of one stored chunk as CSV lines (see ``csv_rows``).

    Runs in a worker thread of the server, where every millisecond of Python holds
    the interpreter the event loop needs: so the common case is text work, not a
    parse and a ``repr`` per value."""
    text = storage.chunk_text(run_id, seq)
    fast = plain_chunk_csv(text)
    return fast if fast is not None else csv_rows(json.loads(text))


def plain_chunk_csv(text: str) -> str | None:
    """``csv_rows(json.loads(text))`` for a compact chunk of numbers and nulls whose
    rows end in their flag list, or None when ``text`` is anything else."""
    if not text.startswith("[[") or not text.endswith("]]]") or _PLAIN_CHUNK.search(text):
        return None
    if ",[]]" in text:
        return None  # rows without flags: a lone empty field is written "" by csv
    body = (
        text[1:-1]
        .replace("]],[", "\n")  # row boundaries
        .replace(",[", ",")  # the flags follow the values
        .replace("null", "")
    )
    if "[" in body[1:] or "]" in body[:-2]:
        return None  # nested otherwise than [values..., [flags]]
    return body[1:-2] + "\n"


def run_json_head(run: dict[str, Any]) -> str:
    """The run without samples as JSON text, open for ``"samples": [...]`` to follow."""
    text = dumps_strict({k: v for k, v in run.items() if k != "samples"})
    return text[:-1] + ("," if len(text) > 2 else "") + '"samples":['


def chunk_rows_text(storage: Storage, run_id: str, seq: int) -> str:
    """The rows of one stored chunk as JSON text without the brackets (verbatim)."""
    return storage.chunk_text(run_id, seq)[1:-1].strip()
