"""``device-check``: every table's smoke profile on one device, every failure collected in one call.

A lent GPU comes with minutes, not hours, and a table run on a new device stops at its first
error. This runs each (table, prior) pair on its own, in process, catches what fails, and goes on,
so that one call reports every place where the device breaks the harness: the exception, its
message and the innermost frames of the project (``benchmark/``, ``priors/``) and of the library
it failed in. A pair that runs is compared with the committed smoke table (``results/TABLE.smoke.json``),
largest difference per metric, so a device that runs but computes something else is seen too
(another device moves the smoke numbers by the cross-machine spread of ``docs/testing.md``: up to
about 25 % of a 20-step fit, so this is a report, not a pass/fail test). On CUDA each pair also
records the device memory it peaked at.

Order: ``no-prior`` on every table first (the harness's own paths), then the other priors, table1
first. ``budget_s`` stops starting new pairs once it is spent; those are reported as not run.
"""

from __future__ import annotations

import json
import math
import platform
import time
import traceback
from pathlib import Path

PROJECT_PARTS = ("benchmark", "priors")
TABLE_ORDER = ("table1", "sls", "reconstruction", "inbetween", "denoise")


def pair_order(tables: list[str], priors_of: dict[str, list[str]]) -> list[tuple[str, str]]:
    """(table, prior) in the order they run: no-prior on every table, then each table's other priors."""
    first = [(t, "no-prior") for t in tables if "no-prior" in priors_of[t]]
    return first + [(t, p) for t in tables for p in priors_of[t] if p != "no-prior"]


def failure_record(exc: BaseException) -> dict:
    """What failed and where: the exception and the innermost frames in the project and outside it."""
    frames = traceback.extract_tb(exc.__traceback__)

    def where(f):
        return f"{f.filename}:{f.lineno} ({f.name}): {(f.line or '').strip()}"

    ours = [f for f in frames if any(f"/{part}/" in f.filename.replace("\\", "/") for part in PROJECT_PARTS)]
    return {
        "error": type(exc).__name__,
        "message": str(exc).strip().splitlines()[0][:500] if str(exc).strip() else "",
        "project_frame": where(ours[-1]) if ours else None,
        "innermost_frame": where(frames[-1]) if frames else None,
        "traceback": "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))[-4000:],
    }


def golden_differences(table: dict, golden_path: Path, prior: str) -> dict:
    """Per metric, the largest |difference| of ``prior``'s row against the committed smoke table and
    that difference relative to the committed value; ``{"note": ...}`` where there is nothing to compare."""
    from benchmark.tools.compare import compare_tables, load_table_json, only_priors

    if not golden_path.is_file():
        return {"note": f"no {golden_path.name} to compare with"}
    golden = load_table_json(golden_path)
    if prior not in [r["prior"] for r in golden["rows"]]:
        return {"note": f"{golden_path.name} has no row for {prior}"}
    _, rows = compare_tables(only_priors(golden, [prior], str(golden_path)), only_priors(table, [prior], "this run"))
    out: dict = {}
    for row in rows:
        if row.get("kind") != "cell" or row.get("diff") is None:
            continue
        largest = out.get(row["metric"])
        if largest is None or abs(row["diff"]) > largest["max_abs"]:
            out[row["metric"]] = {"max_abs": abs(row["diff"]),
                                  "rel": abs(row["diff"]) / abs(row["a"]) if row["a"] else math.inf}
    mismatched = sorted({r["field"] for r in rows if r.get("kind") == "header" and r["status"] == "mismatch"})
    if mismatched:
        out["note"] = f"differs from {golden_path.name} in {', '.join(mismatched)}"
    return out


def environment(device: str) -> dict:
    import torch

    env = {"torch": torch.__version__, "python": platform.python_version(), "device": device,
           "cuda_available": torch.cuda.is_available()}
    if device.startswith("cuda") and torch.cuda.is_available():
        env["gpu"] = torch.cuda.get_device_name(torch.device(device))
        env["cuda"] = torch.version.cuda
    return env


def check_device(device: str, tables: list[str], priors: list[str] | None, out: Path, results_dir: Path,
                 budget_s: float = 480.0, seed: int = 0, log=print) -> dict:
    """Run each (table, prior) pair's smoke table on ``device``; see the module docstring. Returns
    the report (also written to ``out``/device-check.json and .md)."""
    from benchmark.body import get_body
    from benchmark.run.catalog import default_priors, get_profile, load_table_spec
    from benchmark.run.table_run import run_table

    specs = {t: load_table_spec(t) for t in tables}
    priors_of = {t: list(priors or default_priors(specs[t])) for t in tables}
    report = {"environment": environment(device), "budget_s": budget_s, "pairs": []}
    start = time.monotonic()
    try:
        body = get_body("anny", device=device)
    except Exception as exc:  # the body itself does not load on the device: nothing else can run
        report["body"] = {"status": "failed", **failure_record(exc)}
        log(f"body on {device}: FAILED {exc.__class__.__name__}: {exc}")
        _write(report, out)
        return report
    report["body"] = {"status": "ok", "seconds": round(time.monotonic() - start, 1)}
    for table, prior in pair_order(tables, priors_of):
        entry = {"table": table, "prior": prior}
        elapsed = time.monotonic() - start
        if elapsed > budget_s:
            entry["status"] = "not run (budget spent)"
            report["pairs"].append(entry)
            continue
        t0 = time.monotonic()
        _reset_peak(device)
        try:
            result = run_table(specs[table], get_profile("smoke", table=table), [prior], body, device, seed,
                               out / table / prior, backend_options={"jobs": 1})
        except Exception as exc:
            entry.update(status="failed", **failure_record(exc))
            log(f"{table:15s} {prior:22s} FAILED after {time.monotonic() - t0:.0f} s: {entry['error']}: {entry['message'][:160]}")
            log(f"{'':38s} at {entry['project_frame'] or entry['innermost_frame']}")
        else:
            if result["failures"]:  # the runner stores what it could and lists the units that raised
                first = next(iter(result["failures"]))
                entry.update(status="failed", seconds=round(time.monotonic() - t0, 1),
                             **failure_record(result.get("errors", {}).get(first) or RuntimeError(result["failures"][first])))
                entry["message"] = f"{len(result['failures'])} unit(s) failed; {first}: {entry['message']}"[:500]
                log(f"{table:15s} {prior:22s} FAILED: {entry['error']}: {entry['message'][:160]}")
                log(f"{'':38s} at {entry['project_frame'] or entry['innermost_frame']}")
            else:
                entry.update(status="ok", seconds=round(time.monotonic() - t0, 1), peak_gib=_peak_gib(device),
                             against_smoke_golden=golden_differences(result["table"], results_dir / f"{table}.smoke.json",
                                                                     prior))
                log(f"{table:15s} {prior:22s} ok in {entry['seconds']:.0f} s")
        report["pairs"].append(entry)
    report["seconds"] = round(time.monotonic() - start, 1)
    _write(report, out)
    return report


def _reset_peak(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats(torch.device(device))


def _peak_gib(device: str) -> float | None:
    """The device memory the pair's run peaked at (GiB), for sizing the full profile's batches; None on the CPU."""
    import torch

    if not device.startswith("cuda"):
        return None
    return round(torch.cuda.max_memory_allocated(torch.device(device)) / 2**30, 2)


def failed(report: dict) -> bool:
    return report.get("body", {}).get("status") != "ok" or any(p["status"] == "failed" for p in report["pairs"])


def format_markdown(report: dict) -> str:
    env = report["environment"]
    lines = [f"# device-check on {env['device']}" + (f" ({env['gpu']}, CUDA {env['cuda']})" if "gpu" in env else ""),
             "", f"torch {env['torch']}, python {env['python']}; every table's smoke profile, one prior at a time.", ""]
    body = report.get("body", {})
    if body.get("status") != "ok":
        lines += [f"**The body failed to load**: {body.get('error')}: {body.get('message')}",
                  f"at {body.get('project_frame') or body.get('innermost_frame')}", ""]
        return "\n".join(lines) + "\n"
    lines += ["| table | prior | status | seconds | peak GiB | where / largest difference from the smoke golden |",
              "| --- | --- | --- | --: | --: | --- |"]
    for p in report["pairs"]:
        if p["status"] == "failed":
            detail = f"{p['error']}: {p['message'][:200]} at `{p['project_frame'] or p['innermost_frame']}`"
        elif p["status"] == "ok":
            diffs = p.get("against_smoke_golden", {})
            detail = "; ".join(f"{m} {d['max_abs']:.2f} ({100 * d['rel']:.1f} %)" for m, d in diffs.items()
                               if isinstance(d, dict)) or diffs.get("note", "")
        else:
            detail = ""
        peak = "" if p.get("peak_gib") is None else p["peak_gib"]
        lines.append(f"| {p['table']} | {p['prior']} | {p['status']} | {p.get('seconds', '')} | {peak} | "
                     f"{detail.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def _write(report: dict, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "device-check.json").write_text(json.dumps(report, indent=1, sort_keys=True), encoding="utf-8")
    (out / "device-check.md").write_text(format_markdown(report), encoding="utf-8")
