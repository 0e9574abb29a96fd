"""Run web/src/stability.ts under node: the browser's loop arithmetic, for tests that
compare it with the server's."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

from tests.support.paths import REPO


def evaluate(cases: list[dict[str, Any]], tmp_path: Path, expression: str) -> list[Any]:
    """``expression`` for each case ``c``, with stability.ts's exports in scope as ``s``
    (and ``loopStable``, ``modelMargins`` by name), compiled with the web client's
    TypeScript and run under node."""
    tsc = REPO / "web" / "node_modules" / ".bin" / "tsc"
    node = shutil.which("node")
    assert tsc.exists() and node, "the web client's packages and node are needed (scripts/test.sh)"
    out = tmp_path / "stability"
    source = str(REPO / "web" / "src" / "stability.ts")
    arguments = ["--target", "es2022", "--module", "es2022", "--outDir", str(out), source]
    subprocess.run([str(tsc), *arguments], check=True)
    module = out / "stability.mjs"
    (out / "stability.js").rename(module)
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
