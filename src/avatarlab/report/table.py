"""A report table: named columns, rows of values, written as CSV (every column, full precision) and as Markdown and
HTML for reading: at most `MAX_SHOWN` columns (the table's `shown`, else its first columns that hold a value; the
rest are named under it), each number rounded to what its noise justifies (to the first significant digit of its
95 % CI, plus one; without a CI: 2 decimals, 3 significant digits below 1), and, for a table with a `Headline`, the
best row marked and one sentence saying which row is best and whether it beats its best trivial baseline beyond the
noise. A number a run could not measure is written "missing", never filled in."""
from __future__ import annotations

import csv
import html
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

from avatarlab.runtime.io import atomic_path

MISSING = "missing"
NOT_FINITE = "not finite"  # a NaN or an infinity is shown as what it is, never as a number
MAX_SHOWN = 8  # columns a reader sees; the CSV has them all


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


def decimals_for(ci) -> int | None:
    """Decimals that a value with this 95 % CI half-width deserves: its first significant digit, plus one."""
    if not isinstance(ci, (int, float)) or isinstance(ci, bool) or not math.isfinite(ci) or ci <= 0:
        return None
    return int(min(max(1 - math.floor(math.log10(ci)), 0), 4))


def rounded(value, ci=None) -> str:
    """A value as a reader sees it (see the module's doc); not a number: as `fmt`."""
    if not isinstance(value, float) or not math.isfinite(value):
        return fmt(value)
    digits = decimals_for(ci)
    if digits is not None:
        return f"{value:.{digits}f}"
    if value == 0 or abs(value) >= 1:
        return f"{value:.1f}" if abs(value) >= 100 else f"{value:.2f}"
    return f"{value:.3f}" if abs(value) >= 0.01 else f"{value:.3g}"


def noise_of(row: dict, column: str, named: dict | None = None):
    """The 95 % CI half-width that goes with a column (`<column>_ci95`, or the column `named` maps it to), if the row
    has one."""
    for key in ((named or {}).get(column), f"{column}_ci95"):
        if key and isinstance(row.get(key), (int, float)):
            return row[key]
    return None


@dataclass(frozen=True)
class Headline:
    """Which row is best and does it beat its baseline: `metric` ranks the rows (`higher` is better), `labels` name
    a row, `gain` is its gain over its best trivial baseline (`gain_ci`: that gain's 95 % CI half-width, if any),
    `baseline` the column naming that baseline. each=True: the rows are not rivals (one per subject): no best row,
    the sentence says for each whether it beats its baseline."""
    metric: str
    labels: tuple[str, ...]
    higher: bool = True
    gain: str = "gain"
    gain_ci: str | None = "gain_ci95"
    baseline: str | None = "best_baseline"
    each: bool = False
    versus: str | None = None  # the baseline's name where no column names it (e.g. "the cross-fade")


def verdict_words(gain, ci, baseline: str | None = None, versus: str | None = None) -> str:
    """Whether a gain over the best trivial baseline is one: beyond its 95 % CI, within it, or none."""
    it = versus or (f"its best baseline ({baseline})" if baseline else "its best baseline")
    if gain is None:
        return "has no baseline comparison"
    if gain <= 0:
        return f"does NOT beat {it} ({rounded(gain, ci)})"
    if ci is None:
        return f"beats {it} by {rounded(gain)} (one run: no noise estimate)"
    if gain > ci:
        return f"beats {it} by {rounded(gain, ci)}, beyond the 95 % CI (±{rounded(ci, ci)})"
    return f"is ahead of {it} by {rounded(gain, ci)}, within the noise (95 % CI ±{rounded(ci, ci)})"


class Table:
    def __init__(self, name: str, title: str, columns: list[str], note: str = "", shown: list[str] | None = None,
                 headline: Headline | None = None, ci_columns: dict[str, str] | None = None):
        """shown: the columns a reader sees (default: the first `MAX_SHOWN` that hold a value); ci_columns: a
        column's 95 % CI column where it is not `<column>_ci95` (e.g. {"gain_iod": "clip_gain_ci95"})."""
        self.name, self.title, self.columns, self.note, self.rows = name, title, columns, note, []
        self.shown, self.headline, self.ci_columns = shown, headline, dict(ci_columns or {})

    def add(self, **row):
        self.rows.append(row)

    def visible(self) -> tuple[list[str], list[str]]:
        """(the columns a reader sees, the other columns that hold a value: in the CSV only)."""
        filled = [c for c in self.columns if any(r.get(c) is not None for r in self.rows)] or self.columns
        if self.shown is not None:
            shown = [c for c in self.shown if c in self.columns]
        else:
            shown = [c for c in filled if not c.endswith("_ci95")][:MAX_SHOWN]
        paired = {self.ci_columns.get(c, f"{c}_ci95") for c in shown}
        return shown, [c for c in filled if c not in shown and c not in paired]

    def best_row(self) -> dict | None:
        h = self.headline
        if h is None or h.each:
            return None
        rows = [r for r in self.rows if isinstance(r.get(h.metric), (int, float)) and math.isfinite(r[h.metric])]
        if not rows:
            return None
        return (max if h.higher else min)(rows, key=lambda r: r[h.metric])

    def label(self, row: dict) -> str:
        return " / ".join(str(row.get(k)) for k in (self.headline.labels if self.headline else self.columns[:1]))

    def sentence(self) -> str:
        """One sentence: the best row and whether it beats its best trivial baseline beyond the noise (each=True:
        for every row)."""
        h = self.headline
        if h is None or not self.rows:
            return ""

        def part(row: dict) -> str:
            ci = row.get(h.gain_ci) if h.gain_ci else None
            return f"{self.label(row)} {verdict_words(row.get(h.gain), ci, row.get(h.baseline) if h.baseline else None, h.versus)}"

        if h.each:
            return "; ".join(part(r) for r in self.rows) + "."
        best = self.best_row()
        if best is None:
            return f"No row has a {h.metric}."
        return (f"Best by {h.metric} ({'higher' if h.higher else 'lower'} is better): {self.label(best)} "
                f"({rounded(best[h.metric], noise_of(best, h.metric, self.ci_columns))}); {part(best)}.")

    def csv(self) -> str:
        out = io.StringIO()
        writer = csv.DictWriter(out, self.columns, extrasaction="ignore")
        writer.writeheader()
        for row in self.rows:
            writer.writerow({c: cell(row.get(c)) for c in self.columns})
        return out.getvalue()

    def cells(self, row: dict, columns: list[str]) -> list[str]:
        """A row's cells as a reader sees them: a value with its CI as 'value ± ci', rounded to the CI."""
        out = []
        for c in columns:
            value, ci = row.get(c), noise_of(row, c, self.ci_columns)
            text = rounded(value, ci)
            ci_column = self.ci_columns.get(c, f"{c}_ci95")
            if ci is not None and isinstance(value, float) and ci_column not in columns:
                text += f" ± {rounded(ci, ci)}"
            out.append(text)
        return out

    def layout(self) -> tuple[list[str], list[str], dict | None, str]:
        """What both renderings show: (columns shown, columns in the CSV only, the best row, the sentence)."""
        shown, rest = self.visible()
        return shown, rest, self.best_row(), self.sentence()

    def markdown(self) -> str:
        shown, rest, best, sentence = self.layout()
        lines = [f"### {self.title}", ""]
        if sentence:
            lines += [f"**{sentence}**", ""]
        if self.note:
            lines += [self.note, ""]
        lines += ["| " + " | ".join(shown) + " |", "|" + "---|" * len(shown)]
        for row in self.rows:
            cells = self.cells(row, shown)
            if row is best:
                cells[0] = f"**{cells[0]}** (best)"
            lines.append("| " + " | ".join(cells) + " |")
        if not self.rows:
            lines.append("| " + " | ".join(["(no runs)"] + [""] * (len(shown) - 1)) + " |")
        if rest:
            lines += ["", f"More columns in `{self.name}.csv`: {', '.join(rest)}."]
        return "\n".join(lines) + "\n"

    def html(self) -> str:
        """The same as `markdown`, as an HTML fragment (the Snakemake report's landing page)."""
        shown, rest, best, sentence = self.layout()
        esc = html.escape
        parts = [f"<h3>{esc(self.title)}</h3>"]
        if sentence:
            parts.append(f'<p class="headline"><b>{esc(sentence)}</b></p>')
        if self.note:
            parts.append(f'<p class="note">{esc(self.note)}</p>')
        parts.append("<table><thead><tr>" + "".join(f"<th>{esc(c)}</th>" for c in shown) + "</tr></thead><tbody>")
        for row in self.rows:
            cells = [esc(c) for c in self.cells(row, shown)]
            if row is best:
                cells[0] = f"<b>{cells[0]}</b> (best)"
            parts.append(('<tr class="best">' if row is best else "<tr>")
                         + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
        if not self.rows:
            parts.append(f'<tr><td colspan="{len(shown)}">(no runs)</td></tr>')
        parts.append("</tbody></table>")
        if rest:
            parts.append(f'<p class="more">More columns in {esc(self.name)}.csv: {esc(", ".join(rest))}.</p>')
        return "\n".join(parts) + "\n"

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
