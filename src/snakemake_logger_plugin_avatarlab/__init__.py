"""A quiet console for the avatarlab workflow (`snakemake --logger avatarlab`, what `make main` uses): one line per
finished step with the count, the elapsed time and an estimate of what is left; a failed step's rule, its log's path
and the log's last lines; warnings and errors as they come. Everything else stays in Snakemake's own log file
(`.snakemake/log/`), whose path is the last line.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from snakemake_interface_logger_plugins.base import LogHandlerBase
from snakemake_interface_logger_plugins.common import LogEvent
from snakemake_interface_logger_plugins.settings import LogHandlerSettingsBase


@dataclass
class LogHandlerSettings(LogHandlerSettingsBase):
    pass


def clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"


def tail(path: str, lines: int = 15) -> list[str]:
    try:
        return Path(path).read_text(errors="replace").splitlines()[-lines:]
    except OSError:
        return []


class LogHandler(LogHandlerBase):
    def __post_init__(self) -> None:
        self.start = time.monotonic()
        self.rules: dict[int, str] = {}
        self.started: dict[int, float] = {}
        self.last_rule = ""

    def say(self, text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    def emit(self, record) -> None:
        event = getattr(record, "event", None)
        if event == LogEvent.JOB_INFO:
            jobid = getattr(record, "jobid", None)
            self.rules[jobid] = getattr(record, "rule_name", "") or "?"
            self.started[jobid] = time.monotonic()
        elif event == LogEvent.JOB_FINISHED:
            self.last_rule = self.rules.get(getattr(record, "job_id", None), "")
        elif event == LogEvent.PROGRESS:
            done, total = int(record.done), int(record.total)
            elapsed = time.monotonic() - self.start
            left = elapsed / done * (total - done) if done else 0.0
            self.say(f"[{clock(elapsed)}] {done} of {total} steps done ({self.last_rule}); about {clock(left)} left")
        elif event == LogEvent.JOB_ERROR:
            log = getattr(record, "log", None) or []
            logs = [str(p) for p in (log if isinstance(log, (list, tuple)) else [log])]
            self.say(f"FAILED: step {getattr(record, 'rule_name', '?')} (job {getattr(record, 'jobid', '?')}); "
                     f"its log: {', '.join(logs) or 'none'}")
            for path in logs[:1]:
                for line in tail(path):
                    self.say(f"    {line}")
        elif event == LogEvent.RUN_INFO:
            stats = getattr(record, "stats", None) or {}
            total = stats.get("total") if isinstance(stats, dict) else None
            if total:
                self.say(f"avatarlab: {total} step{'s' if total != 1 else ''} to run")
        elif event is None and record.levelno >= 30:
            text = self.format(record) if self.formatter else record.getMessage()
            if text.strip():
                self.say(text)
        elif event is None and "Complete log" in str(record.getMessage()):
            self.say(record.getMessage())

    @property
    def writes_to_stream(self) -> bool:
        return True

    @property
    def writes_to_file(self) -> bool:
        return False

    @property
    def has_filter(self) -> bool:
        return True

    @property
    def has_formatter(self) -> bool:
        return True

    @property
    def needs_rulegraph(self) -> bool:
        return False
