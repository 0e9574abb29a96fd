"""The generated TypeScript of the wire schema: every model of ``servotune.schema`` is
rendered, a REST request's defaulted field is optional, a response's fields are all
sent, a documented shape's defaulted field may be absent, and the checked-in
``web/src/schema.gen.ts`` is current."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from types import ModuleType

from pydantic import BaseModel

from servotune import schema, schema_ts
from tests.support.paths import REPO

# Models of the schema that are not bodies the web client reads or sends: the command
# request is free-form (its fields come from the descriptor).
# ``_Shape`` is the base of the documented shapes, not a body.
NOT_RENDERED = {"CommandRequest", "_Shape"}


def schema_modules() -> list[ModuleType]:
    """The modules of the ``servotune.schema`` package."""
    return [
        importlib.import_module(f"{schema.__name__}.{info.name}")
        for info in pkgutil.iter_modules(schema.__path__)
    ]


def declared_in(module: ModuleType) -> dict[str, object]:
    """The names ``module``'s source binds at its top level by a class or an assignment
    (not the ones it imports)."""
    names: list[str] = []
    for node in ast.parse(inspect.getsource(module)).body:
        if isinstance(node, ast.ClassDef):
            names.append(node.name)
        elif isinstance(node, ast.Assign):
            names.extend(t.id for t in node.targets if isinstance(t, ast.Name))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.append(node.target.id)
    return {name: getattr(module, name) for name in names if name != "__all__"}


def test_the_schema_package_was_found() -> None:
    # An empty walk would make the checks below pass vacuously.
    assert schema.RunMetrics.__module__ in {m.__name__ for m in schema_modules()}


def test_every_public_name_is_importable_from_servotune_schema() -> None:
    """The package is the one place to import from: every public name its modules
    define is re-exported (the same object), and ``__all__`` lists exactly those."""
    public = {
        name: value
        for module in schema_modules()
        for name, value in declared_in(module).items()
        if not name.startswith("_")
    }
    assert len(public) > 90, sorted(public)
    missing = {name for name, value in public.items() if getattr(schema, name, None) is not value}
    assert missing == set()
    assert set(schema.__all__) == set(public)


def test_every_schema_model_is_rendered() -> None:
    rendered = {
        m.__name__
        for m in [
            *schema_ts.MODELS,
            *schema_ts.REST_RESPONSES,
            *schema_ts.REST_REQUESTS,
            *schema_ts.REST_SHAPES,
        ]
    }
    declared = {
        name
        for module in schema_modules()
        for name, value in declared_in(module).items()
        if inspect.isclass(value) and issubclass(value, BaseModel)
    }
    assert len(declared) > 70, declared
    assert declared - NOT_RENDERED - rendered == set()


def test_request_defaults_are_optional_and_responses_are_complete() -> None:
    text = schema_ts.render()
    request = text.split("export interface BenchTestRequest {", 1)[1].split("}", 1)[0]
    assert "  kind: BenchKind;" in request  # required: no default
    assert "  distance?: number;" in request
    response = text.split("export interface BenchLimits {", 1)[1].split("}", 1)[0]
    assert "  min_position_counts: number | null;" in response
    assert "?" not in response


def test_a_shapes_defaulted_field_may_be_absent() -> None:
    """A body built as a dict (a bench run) leaves out what a run does not have."""
    text = schema_ts.render()
    run = text.split("export interface BenchRun {", 1)[1].split("}", 1)[0]
    assert "  metrics: RunMetrics | null;" in run  # always there, null when not computed
    assert "  quality?: RunQuality | null;" in run  # absent on runs stored without one
    assert "  return?: RunReturn | null;" in run  # the JSON key, not the Python name
    assert "  autotune?: Record<string, unknown> | null;" in run


def test_shapes_of_rest_bodies() -> None:
    assert schema_ts.ts_type(tuple[int | float, int | float]) == "[number, number]"
    assert schema_ts.ts_type(dict[str, int | float | None]) == "Record<string, number | null>"


def test_checked_in_file_is_current() -> None:
    path = REPO / "web" / "src" / "schema.gen.ts"
    assert schema_ts.main(["--check", str(path)]) == 0


def test_the_bench_pwm_bound_is_the_models_output_full_scale() -> None:
    """``BenchLimits.max_pwm``'s upper bound is written as a number in the schema (which
    imports no tuning); it must be the output full scale the models use."""
    from servotune.schema import BenchLimits
    from servotune.tuning.plants import OUTPUT_FULL_SCALE

    for model in (BenchLimits, schema.AutoTuneRequest):
        field = model.model_fields["max_pwm"]
        bound = next(m.le for m in field.metadata if hasattr(m, "le"))
        assert bound == OUTPUT_FULL_SCALE, model


def test_the_autotune_request_defaults_to_the_tuning_default_target() -> None:
    """The request's margin preset is written as a literal in the schema too."""
    from servotune.tuning.targets import DEFAULT_PRESET

    assert schema.AutoTuneRequest.model_fields["margins"].default == DEFAULT_PRESET


def test_the_autotune_bodies_are_generated_not_device_specific() -> None:
    """The auto-tune's REST bodies are generated, with gains by parameter name (any
    device's descriptor) and the session's result either a verification or how it
    ended early; a session as the server starts it has that shape."""
    from servotune.autotune.session import IdentifyRequest, Session

    text = schema_ts.render()
    proposal = text.split("export interface AutoTuneProposal {", 1)[1].split("}", 1)[0]
    assert "  gains: Record<string, number>;" in proposal
    assert "  predicted: RunMetrics;" in proposal
    assert "  recommendation: AutoTuneRecommendation;" in proposal
    session = text.split("export interface AutoTuneSession {", 1)[1].split("}", 1)[0]
    assert "  result: AutoTuneResult | AutoTuneStopped | null;" in session
    assert "  state: AutoTuneState;" in session
    fresh = Session("line-0").to_dict()
    schema.AutoTuneSession.model_validate(fresh, strict=True)
    started = Session("line-0")
    started.reset(IdentifyRequest(max_pwm=60, max_distance_counts=4000))
    schema.AutoTuneSession.model_validate(started.to_dict(), strict=True)


def test_a_subclass_extends_its_rendered_parent() -> None:
    text = schema_ts.render()
    detail = text.split("export interface BenchRunDetail extends BenchRun {", 1)[1]
    assert detail.split("}", 1)[0].strip() == "samples: ((number | number[] | null)[])[];"


def test_the_run_shapes_name_the_fields_the_bench_stores() -> None:
    """The run export the import takes (``bench.files.RunExport``) is the run as listed,
    with the bench's own metrics model: the same field names, so the documented shape
    and the TypeScript cannot drift from what the bench writes."""
    from servotune.bench.files import RunExport
    from servotune.bench.metrics import DEFINITIONS, compute_metrics

    assert RunExport.model_fields["metrics"].annotation == schema.RunMetrics | None
    computed = compute_metrics([0.0, 0.1, 0.2], [0.0, 5.0, 10.0], t0_s=0.0, y0=0.0, y_final=10.0)
    assert type(computed) is schema.RunMetrics
    assert set(DEFINITIONS) == set(schema.RunMetrics.model_fields)
    listed = {f.alias or name for name, f in schema.BenchRun.model_fields.items()}
    exported = {f.alias or name for name, f in RunExport.model_fields.items()}
    assert listed - exported == set()
    assert exported - listed == set()
