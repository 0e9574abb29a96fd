"""Run web/src/stability.ts under node: the browser's loop arithmetic, for tests that
compare it with the server's."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

from tests.support.paths import REPO


def evaluate(cases: list[dict[str, Any]], tmp_path: Path, expression: str) -> list[Any]:
    """``expression`` for each case ``c``, with stability.ts's exports in scope as ``s``
    (and ``loopStable``, ``modelMargins`` by name), compiled with the web client's
    TypeScript (``_compiled``) and run under node."""
    node = shutil.which("node")
    assert node, "node is needed (scripts/test.sh)"
    module = _compiled(tmp_path)
    script = (
        f"import * as s from {json.dumps(str(module))};"
        "const { loopStable, modelMargins } = s;"
        "let text = '';"
        "process.stdin.on('data', (d) => (text += d));"
        "process.stdin.on('end', () => {"
        f"  const out = JSON.parse(text).map((c) => {expression});"
        "  process.stdout.write(JSON.stringify(out));"
        "});"
    )
    result = subprocess.run(
        [node, "--input-type=module", "-e", script],
        input=json.dumps(cases),
        capture_output=True,
        text=True,
        check=True,
    )
    values: list[Any] = json.loads(result.stdout)
    return values


def _compiled(tmp_path: Path) -> Path:
    """stability.ts compiled to an ES module, once per test session and source: into
    the session's base temporary directory (``tmp_path``'s parent), named by the
    source's digest, so that an edited stability.ts is compiled again."""
    tsc = REPO / "web" / "node_modules" / ".bin" / "tsc"
    assert tsc.exists(), "the web client's packages are needed (scripts/test.sh)"
    source = REPO / "web" / "src" / "stability.ts"
    digest = hashlib.sha256(source.read_bytes()).hexdigest()[:16]
    out = tmp_path.parent / f"stability-ts-{digest}"
    module = out / "stability.mjs"
    if module.exists():
        return module
    build = tmp_path / "stability"
    arguments = ["--target", "es2022", "--module", "es2022", "--outDir", str(build), str(source)]
    subprocess.run([str(tsc), *arguments], check=True)
    (build / "stability.js").rename(build / "stability.mjs")
    build.rename(out)  # whole, or not at all
    return module
