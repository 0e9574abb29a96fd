// Importing a run exported from servotune: its .json and .csv, picked together or one
// after the other.
import { ApiError, writeHeaders } from "../../api";
import { h, setText } from "../../dom";
import { errorText, statusLabel } from "../feedback";
import { shortId } from "./kinds";

export class RunImport {
  readonly input: HTMLInputElement;
  readonly status: HTMLElement;
  readonly button: HTMLButtonElement;
  private pending: { json?: File; csv?: File } = {};

  constructor(
    private readonly axisId: string,
    /** The run was stored under ``id``. */
    private readonly onImported: (id: string) => Promise<void>,
  ) {
    this.input = h("input", {
      type: "file",
      multiple: true,
      accept: ".json,.csv,application/json,text/csv",
      testid: "bench-import-file",
      hidden: true,
    });
    this.input.addEventListener("change", () => void this.importFiles());
    this.status = h("span", { class: "bench-import-status", testid: "bench-import-status" });
    this.button = h(
      "button",
      {
        class: "btn small",
        testid: "bench-import",
        title: "Import a run exported from servotune: pick its .json and its .csv (both at once, or one after the other)",
        onclick: () => this.input.click(),
      },
      "Import…",
    );
  }

  private async importFiles(): Promise<void> {
    const files = [...(this.input.files ?? [])];
    this.input.value = "";
    try {
      for (const file of files) {
        // Only the start of a file is read to tell JSON from CSV: a run can be tens of
        // megabytes, and the server parses it (sent as multipart, up to 64 MiB).
        const head = await file.slice(0, 64).text();
        if (/\.json$/i.test(file.name) || head.trimStart().startsWith("{")) this.pending.json = file;
        else this.pending.csv = file;
      }
    } catch (error) {
      this.pending = {};
      this.setStatus("error", `cannot read the file: ${errorText(error)}`);
      return;
    }
    const { json, csv } = this.pending;
    if (json === undefined || csv === undefined) {
      this.setStatus("pending", json === undefined ? `${csv?.name}: now pick the run's .json` : `${json.name}: now pick the run's .csv`);
      return;
    }
    this.pending = {};
    this.setStatus("pending", "importing …");
    try {
      const { id } = await importRunFiles(this.axisId, json, csv);
      this.setStatus("ok", `✓ imported as ${shortId(id)}`);
      await this.onImported(id);
    } catch (error) {
      this.setStatus("error", `✗ import: ${statusLabel(error)} — ${errorText(error)}`);
    }
  }

  private setStatus(kind: string, text: string): void {
    this.status.dataset.kind = kind;
    setText(this.status, text);
    this.status.title = text;
  }
}

/** ``POST /api/axes/{id}/bench/runs/import`` as multipart (run.json + samples.csv). */
async function importRunFiles(axisId: string, json: File, csv: File): Promise<{ id: string }> {
  const form = new FormData();
  form.append("meta", json, json.name);
  form.append("csv", csv, csv.name);
  let response: Response;
  try {
    const headers = await writeHeaders();
    response = await fetch(`/api/axes/${encodeURIComponent(axisId)}/bench/runs/import`, { method: "POST", body: form, headers, credentials: "same-origin" });
  } catch (error) {
    throw new ApiError(0, `server unreachable: ${(error as Error).message}`, null);
  }
  let body: unknown = null;
  try {
    body = await response.json();
  } catch {
    body = null;
  }
  if (!response.ok) {
    const b = (body ?? {}) as { detail?: unknown; field?: unknown };
    const detail = typeof b.detail === "string" ? b.detail : `HTTP ${response.status} ${response.statusText}`;
    throw new ApiError(response.status, detail, typeof b.field === "string" ? b.field : null);
  }
  return body as { id: string };
}
