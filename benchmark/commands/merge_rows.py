"""``merge-rows``: a table with some priors' rows replaced by a new run of them (:mod:`benchmark.run.table_merge`)."""

from __future__ import annotations

import json
from pathlib import Path

from benchmark.commands.common import HelpFormatter


def _read_table(path: str, what: str) -> dict:
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{what} {path}: no such file (a table JSON: results/<table>.<profile>.json or <run>/<table>.json)")
    try:
        table = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{what} {path}: not JSON ({e}); give a table JSON written by `python -m benchmark run`") from None
    if not isinstance(table, dict) or not isinstance(table.get("rows"), list):
        raise ValueError(f"{what} {path}: no field 'rows': not a table JSON written by `python -m benchmark run`")
    return table


def _cmd_merge_rows(args) -> int:
    from benchmark.run.table_merge import replace_rows
    from benchmark.core.outdir import check_out_dir
    from benchmark.run.writers import FORMATS, write_table

    if args.stem is not None and (not args.stem or Path(args.stem).name != args.stem or args.stem in (".", "..")):
        raise ValueError(f"--stem {args.stem!r}: must be a plain file name without a folder (e.g. table1.quick); "
                         "give the folder with --out")
    out = check_out_dir(args.out)
    base, new = _read_table(args.base, "BASE"), _read_table(args.new, "NEW")
    merged = replace_rows(base, new, source=args.new, base_source=args.base)
    stem = args.stem or merged["table"]
    targets = [out / f"{stem}.{fmt}" for fmt in FORMATS]
    base_file, new_file = Path(args.base).resolve(), Path(args.new).resolve()
    inputs = {new_file: "NEW", base_file: "BASE (and NEW)" if base_file == new_file else "BASE"}
    clash = [f"{t} is {inputs[t.resolve()]}" for t in targets if t.resolve() in inputs]
    if clash:
        raise FileExistsError(f"--out {out} --stem {stem}: {'; '.join(clash)}, which this command reads; write the merged "
                              "table elsewhere (another --out or --stem) and move it over the input once checked")
    existing = [str(t) for t in targets if t.exists()]
    if existing and not args.force:
        raise FileExistsError(f"--out {out}: {', '.join(existing)} exist; choose another --out or --stem, or pass --force to replace them")
    paths = write_table(merged, out, stem=stem)
    rows = ", ".join(r["prior"] for r in new["rows"])
    print(f"{args.base} with the rows of {rows} from {args.new}: {paths['json']} (and {', '.join(str(p) for f, p in paths.items() if f != 'json')})")
    return 0


def add_command(sub) -> None:
    fmt = HelpFormatter
    p = sub.add_parser("merge-rows", formatter_class=fmt,
                       help="a table with some priors' rows replaced by (or added from) a run of those priors under the same rules",
                       description="BASE with every row of NEW in its prior's place (a new prior is appended); "
                                   "the paired comparisons are derived again. Both must share the table, protocol "
                                   "version, profile, sequences, seed, grid and data, e.g. results/table1.quick.json "
                                   "and `python -m benchmark run table1 --prior mine --out DIR`'s DIR/table1.json.")
    p.add_argument("base", help="the table JSON whose other rows are kept")
    p.add_argument("new", help="the table JSON of the run whose rows go in")
    p.add_argument("--out", required=True, help="folder for the merged table (JSON, Markdown, CSV, LaTeX)")
    p.add_argument("--stem", default=None, help="file name stem (default: the table's name)")
    p.add_argument("--force", action="store_true", help="replace existing files of that stem in --out")
    p.set_defaults(func=_cmd_merge_rows)
