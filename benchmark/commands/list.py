"""``list``: the tables, priors, protocols, datasets, body models and profiles."""

from __future__ import annotations


def cmd_list(args) -> int:
    from benchmark.body import BODY_KINDS
    from benchmark.run.catalog import dataset_rows, prior_rows, profile_rows, protocol_rows, table_rows

    sections = [  # each built only when listed: `list tables` imports no prior
        ("tables", table_rows),
        ("priors", prior_rows),
        ("protocols", protocol_rows),
        ("datasets", dataset_rows),
        ("body models", lambda: list(BODY_KINDS.items())),
        ("profiles", profile_rows),
    ]
    for title, make_rows in sections:
        if args.what and args.what != title.split()[0]:
            continue
        rows = make_rows()
        print(f"{title}:")
        if not rows:
            print("  (none)")
        width = max((len(r[0]) for r in rows), default=0)
        for name, desc in rows:
            print(f"  {name.ljust(width)}  {desc}")
        print()
    return 0


def add_command(sub) -> None:
    p = sub.add_parser("list", help="tables, priors, protocols, datasets, body models, profiles")
    p.add_argument("what", nargs="?", choices=["tables", "priors", "protocols", "datasets", "body", "profiles"], default=None)
    p.set_defaults(func=cmd_list)
