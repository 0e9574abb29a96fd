// What each bench metric means: the server's sentences (``definitions`` of
// GET /api/axes/{id}/bench, server/servotune/bench/metrics.py DEFINITIONS), the hover text
// of the metric columns' headers. The bench view sets them when it loads, before it
// lists any run; until then a header's help is the metric's name.

let definitions: Readonly<Record<string, string>> = {};

export function setMetricDefinitions(served: Readonly<Record<string, string>>): void {
  definitions = served;
}

/** "None" in the server's sentences is "—" in the table. */
export function metricHelp(name: string): string {
  const text = definitions[name] ?? name;
  return text.replace(/\bNone\b/g, "—");
}
