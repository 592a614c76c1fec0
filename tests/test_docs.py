"""The documentation as a reader meets it: a README that is a front door, docs it links, and a pipeline picture that
matches the rules.

To redraw the picture after a change of rules (graphviz's `dot`, which `make main` installs as root):
    .venv/bin/python tests/test_docs.py
"""
from __future__ import annotations

import re
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOT = REPO / "docs" / "rulegraph.dot"


def rule_edges(dot_text: str) -> set[tuple[str, str]]:
    """(rule, rule) edges of a `snakemake --rulegraph` DOT text, the target rule `all` left out (node numbers and
    colours differ from one call to the next; the edges do not)."""
    labels = dict(re.findall(r'^\s*(\d+)\[label = "([^"]+)"', dot_text, re.M))
    edges = {(labels[a], labels[b]) for a, b in re.findall(r"^\s*(\d+) -> (\d+)", dot_text, re.M)}
    return {e for e in edges if "all" not in e}


def current_rulegraph() -> str:
    with tempfile.TemporaryDirectory() as work:
        out = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "--rulegraph", "--cores", "1", "-s",
                              str(REPO / "Snakefile"), "--directory", work, "--config", "scale=smoke"],
                             capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_the_pipeline_picture_matches_the_rules():
    committed, now = rule_edges(DOT.read_text()), rule_edges(current_rulegraph())
    assert len(now) > 50
    assert committed == now, ("docs/rulegraph.dot is stale; redraw it with `.venv/bin/python tests/test_docs.py`: "
                              f"new {sorted(now - committed)}, gone {sorted(committed - now)}")
    assert "](docs/rulegraph.svg)" in (REPO / "README.md").read_text(), "the README shows the picture"


def test_the_readme_is_a_front_door_that_links_every_doc():
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    for doc in ("usage.md", "output.md", "method.md", "troubleshooting.md", "equations.md", "experiment-log.md"):
        assert (REPO / "docs" / doc).is_file() and f"(docs/{doc})" in readme, doc
    for command in ("make main", "make test", "make main SCALE=smoke", "make dashboard SCALE=smoke"):
        assert command in readme, command
    assert not re.findall(r"\b[0-9a-f]{7,40}\b", readme.replace("bcd0053", "")), "no commit history in the README"


def test_the_readmes_results_are_copied_from_the_card_they_name():
    """Every number between `<!-- card: docs/results/X.md -->` and `<!-- /card -->` in the README stands, as written,
    in that committed results card (evaluate/results_card.numbers_not_in); without such a block the README says that
    no card is committed."""
    from avatarlab.report.results_card import numbers_not_in

    readme = (REPO / "README.md").read_text()
    blocks = re.findall(r"<!-- card: (\S+) -->(.*?)<!-- /card -->", readme, re.S)
    if not blocks:
        assert "No such card is committed yet" in readme
        return
    for path, text in blocks:
        card = (REPO / path).read_text()
        assert card.startswith("# Results card"), path
        assert numbers_not_in(text.replace(path, ""), card) == [], path


def redraw() -> None:
    text = current_rulegraph()
    labels = dict(re.findall(r'^\s*(\d+)\[label = "([^"]+)"', text, re.M))
    keep = [line for line in text.splitlines()
            if not ((m := re.match(r"^\s*(\d+)\[label", line)) and labels[m.group(1)] == "all")
            and not ((e := re.match(r"^\s*(\d+) -> (\d+)", line)) and "all" in (labels[e.group(1)], labels[e.group(2)]))]
    header = ("// the workflow's rules (snakemake --rulegraph at smoke scale, the target rule `all` left out);\n"
              "// regenerate: see tests/test_docs.py\n")
    DOT.write_text(header + "\n".join(keep) + "\n")
    subprocess.run(["dot", "-Tsvg", str(DOT), "-o", str(DOT.with_suffix(".svg"))], check=True)


if __name__ == "__main__":
    redraw()


def test_no_run_history_in_the_code():
    """Dates and experiment-log citations belong in docs/experiment-log.md, not in docstrings and comments."""
    hits = [f"{p.relative_to(REPO)}:{n}" for p in (REPO / "src").rglob("*.py")
            for n, line in enumerate(p.read_text().splitlines(), 1)
            if re.search(r"\b20\d\d-\d\d-\d\d\b|experiment-log", line)]
    assert not hits, hits
