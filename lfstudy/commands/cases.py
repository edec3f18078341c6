"""``lfstudy cases CONFIG``: the expanded parameter sweep."""

from __future__ import annotations

import argparse

NAME = "cases"
HELP = "print the expanded sweep: one line per case with its id and derived camera figures"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="study config (YAML)")
    p.add_argument("--ids", action="store_true", help="print only the case ids")


def run(args: argparse.Namespace) -> int:
    import pandas as pd

    from lfstudy.study.config import cases_table, load_config

    table = cases_table(load_config(args.config, piv_grid=True))  # the study as it would run
    if args.ids:
        print("\n".join(table.index))
        return 0
    with pd.option_context(
        "display.max_rows", None, "display.max_columns", None, "display.width", 200, "display.max_colwidth", 80
    ):
        print(table.to_string())
    print(f"\n{len(table)} cases")
    return 0
