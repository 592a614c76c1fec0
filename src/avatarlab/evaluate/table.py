"""A report table: named columns, rows of values, written as CSV and Markdown; a number a run could not measure is
written "missing", never filled in."""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from avatarlab.io import atomic_path

MISSING = "missing"
NOT_FINITE = "not finite"  # a NaN or an infinity is shown as what it is, never as a number


def fmt(value, digits: int = 4):
    if value is None:
        return MISSING
    if isinstance(value, float):
        return f"{value:.{digits}f}" if math.isfinite(value) else NOT_FINITE
    return str(value)


def cell(value):
    """A CSV cell: empty for a number not measured, "not finite" for a NaN or an infinity, else the value."""
    if value is None:
        return ""
    return NOT_FINITE if isinstance(value, float) and not math.isfinite(value) else value


class Table:
    def __init__(self, name: str, title: str, columns: list[str], note: str = ""):
        self.name, self.title, self.columns, self.note, self.rows = name, title, columns, note, []

    def add(self, **row):
        self.rows.append(row)

    def csv(self) -> str:
        out = io.StringIO()
        writer = csv.DictWriter(out, self.columns, extrasaction="ignore")
        writer.writeheader()
        for row in self.rows:
            writer.writerow({c: cell(row.get(c)) for c in self.columns})
        return out.getvalue()

    def markdown(self) -> str:
        lines = [f"### {self.title}", ""]
        if self.note:
            lines += [self.note, ""]
        lines += ["| " + " | ".join(self.columns) + " |", "|" + "---|" * len(self.columns)]
        for row in self.rows:
            lines.append("| " + " | ".join(fmt(row.get(c)) for c in self.columns) + " |")
        if not self.rows:
            lines.append("| " + " | ".join(["(no runs)"] + [""] * (len(self.columns) - 1)) + " |")
        return "\n".join(lines) + "\n"

    def write(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        for suffix, text in ((".csv", self.csv()), (".md", self.markdown())):
            with atomic_path(folder / f"{self.name}{suffix}") as tmp:
                tmp.write_text(text)


def read_json(path: Path):
    return json.loads(path.read_text()) if path.is_file() else None


def gain_columns(part: dict, metric: str) -> dict:
    """best baseline's name and value, and the model's gain over it, for one metric of one evaluated part."""
    g = part["gain"].get(metric)
    if g is None:
        return {"best_baseline": None, "baseline": None, "gain": None}
    return {"best_baseline": g["best_baseline"], "baseline": g["baseline"], "gain": g["gain"]}


def not_beating(table: Table, label_keys: tuple[str, ...], gain_key: str = "gain") -> str:
    """A sentence naming the rows whose gain over their best baseline is not positive."""
    rows = [r for r in table.rows if r.get(gain_key) is not None]
    losers = [" / ".join(str(r.get(k)) for k in label_keys) for r in rows if r[gain_key] <= 0]
    if not rows:
        return "No row has a baseline comparison."
    if not losers:
        return f"Every row ({len(rows)}) beats its best trivial baseline."
    return (f"{len(losers)} of {len(rows)} rows do NOT beat their best trivial baseline: {', '.join(losers)}. "
            "Their numbers say nothing about the method.")
