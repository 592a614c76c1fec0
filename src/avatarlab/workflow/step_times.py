"""Where a workflow run's time went: the job time of every rule, read from a Snakemake log.

    python -m avatarlab.workflow.step_times [LOG] [--cores 2]

LOG defaults to the newest `.snakemake/log/*.snakemake.log` of the working directory. A job's time is the span from
the timestamp before its `jobid:` line to the one before its `Finished jobid: N` line (one-second resolution; a job
that never finished, e.g. of a killed run, is counted as unfinished and not timed). Prints per rule the number of
finished jobs, their summed job minutes, their share of all job time and the longest job, then the run's wall time
(first job start to last finish), the summed job time and that sum divided by the cores: the shortest wall time
the same jobs could take on that many one-thread cores. Planning a scale's budget starts from this table
(README: "Where the time goes").
"""
from __future__ import annotations

import argparse
import re
import sys
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from avatarlab.runtime.errors import ConfigError

_STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]\s*$")
_RULE = re.compile(r"^(?:local)?(?:rule|checkpoint) (\w+):\s*$")
_JOBID = re.compile(r"^\s+jobid: (\d+)\s*$")
_FINISHED = re.compile(r"^Finished job(?:id)?:? (\d+)")


@dataclass
class RuleTime:
    jobs: int = 0
    seconds: float = 0.0
    longest: float = 0.0


@dataclass
class StepTimes:
    rules: dict[str, RuleTime] = field(default_factory=dict)
    unfinished: dict[str, int] = field(default_factory=dict)  # rule -> jobs started and never finished
    first_start: datetime | None = None
    last_finish: datetime | None = None

    @property
    def job_seconds(self) -> float:
        return sum(r.seconds for r in self.rules.values())

    @property
    def wall_seconds(self) -> float:
        if self.first_start is None or self.last_finish is None:
            return 0.0
        return (self.last_finish - self.first_start).total_seconds()


def parse_log(path: Path) -> StepTimes:
    """The job times of one Snakemake log. Raises ConfigError (naming the file) if it holds no timed job."""
    try:
        lines = Path(path).read_text(errors="replace").splitlines()
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the Snakemake log ({err.strerror})") from None
    stamp, rule = None, None
    started: dict[str, tuple[str, datetime]] = {}
    times = StepTimes()
    for line in lines:
        if m := _STAMP.match(line):
            stamp = datetime.strptime(" ".join(m.group(1).split()), "%a %b %d %H:%M:%S %Y")
        elif m := _RULE.match(line):
            rule = m.group(1)
        elif (m := _JOBID.match(line)) and rule is not None and stamp is not None:
            started[m.group(1)] = (rule, stamp)
            times.first_start = stamp if times.first_start is None else min(times.first_start, stamp)
            rule = None
        elif (m := _FINISHED.match(line)) and m.group(1) in started and stamp is not None:
            name, start = started.pop(m.group(1))
            seconds = (stamp - start).total_seconds()
            entry = times.rules.setdefault(name, RuleTime())
            entry.jobs, entry.seconds, entry.longest = entry.jobs + 1, entry.seconds + seconds, max(entry.longest,
                                                                                                      seconds)
            times.last_finish = stamp if times.last_finish is None else max(times.last_finish, stamp)
    for name, _ in started.values():
        times.unfinished[name] = times.unfinished.get(name, 0) + 1
    if not times.rules:
        raise ConfigError(f"{path}: no finished Snakemake job in this file (is it a .snakemake/log/*.snakemake.log?)")
    return times


def table(times: StepTimes, cores: int) -> str:
    """Markdown: one row per rule, most job time first, and the summary lines."""
    total = times.job_seconds
    rows = ["| rule | jobs | job minutes | share | longest job (min) |", "| --- | --- | --- | --- | --- |"]
    for name, r in sorted(times.rules.items(), key=lambda item: -item[1].seconds):
        share = 100 * r.seconds / total if total else 0.0
        rows.append(f"| {name} | {r.jobs} | {r.seconds / 60:.1f} | {share:.0f} % | {r.longest / 60:.1f} |")
    rows.append("")
    rows.append(f"wall time {times.wall_seconds / 60:.1f} min (first job start to last finish); job time "
                f"{total / 60:.1f} min in {sum(r.jobs for r in times.rules.values())} jobs; job time / {cores} cores "
                f"= {total / 60 / cores:.1f} min")
    if times.unfinished:
        rows.append("unfinished (not timed): " + ", ".join(f"{k} x{v}" for k, v in sorted(times.unfinished.items())))
    return "\n".join(rows)


def newest_log(workdir: Path) -> Path:
    logs = sorted((workdir / ".snakemake" / "log").glob("*.snakemake.log"))
    if not logs:
        raise ConfigError(f"{workdir / '.snakemake' / 'log'}: no Snakemake log here (run the workflow first)")
    return logs[-1]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("log", nargs="?", type=Path, help="a .snakemake/log/*.snakemake.log (default: the newest)")
    parser.add_argument("--cores", type=int, default=2, help="cores the job time is divided by (default 2)")
    args = parser.parse_args(argv)
    if args.cores < 1:
        parser.error("--cores must be at least 1")
    try:
        path = args.log or newest_log(Path.cwd())
        times = parse_log(path)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"{path}\n")
    print(table(times, args.cores))
    return 0


if __name__ == "__main__":
    sys.exit(main())
