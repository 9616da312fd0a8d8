"""What made a study report: the commands, config files and commits of its rows, and its own.

Every report of :mod:`radarpc.experiments.study` (the training studies' and the FPS study's)
states them at its top, in its figures' footers and metadata, and ends with the study config.
"""
from __future__ import annotations

import datetime as _dt
import shlex
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from radarpc.training.checkpoint import software_record

__all__ = ["Provenance", "provenance"]


@dataclass(frozen=True)
class Provenance:
    """The provenance of a report made from result rows.

    Attributes
    ----------
    made_by : str
        The command that makes the report.
    commands, files, commits : list of str
        The study commands, config files and commits of the rows, the most common first.
    config : dict
        The study config of the latest row.
    own_commit : str
        The commit of the code that makes the report.
    studies : list of str
        ``"NAME (KIND)"`` of the rows' studies.
    n_rows : int
    rows_dir : Path
        Where the rows were read.
    """

    made_by: str
    commands: list[str]
    files: list[str]
    commits: list[str]
    config: dict
    own_commit: str
    studies: list[str]
    n_rows: int
    rows_dir: Path

    __hash__ = None

    @property
    def footer(self) -> str:
        """One line for a figure's foot."""
        return (f"{self.made_by} | study: {self.commands[0]} | rows' commit {', '.join(c[:10] for c in self.commits)} "
                f"| report's commit {self.own_commit[:10]}")

    @property
    def metadata(self) -> dict[str, str]:
        """A figure's metadata (:func:`radarpc.viz.save_figure`)."""
        return {"Title": ", ".join(self.studies), "Description": f"made by: {self.made_by}; study command(s): "
                f"{' ; '.join(self.commands)}; config file(s): {', '.join(self.files)}; commits of the rows: "
                f"{', '.join(self.commits)}; commit of the report: {self.own_commit}", "Software": "radarpc"}

    def header(self, title: str, rows_made_by: str) -> list[str]:
        """The report's first lines: ``title``, when and how it was made, the study commands, config
        files and the commits of the code that made the rows (``rows_made_by``: what that code did)."""
        return [f"# {title}", "",
                f"Made by `{self.made_by}` on {_dt.datetime.now(_dt.timezone.utc).strftime('%Y-%m-%d %H:%M')} UTC "
                f"from {self.n_rows} result rows in `{self.rows_dir}` (code at commit `{self.own_commit[:10]}`).", "",
                "- study command" + ("s" if len(self.commands) > 1 else "") + ": "
                + "; ".join(f"`{c}`" for c in self.commands),
                "- config file" + ("s" if len(self.files) > 1 else "") + ": " + ", ".join(f"`{f}`" for f in self.files)
                + " (the resolved config is at the end)",
                f"- commits of the code that {rows_made_by}: " + ", ".join(f"`{c}`" for c in self.commits), ""]

    def config_section(self) -> list[str]:
        """The report's last lines: the resolved study config of the latest row."""
        import yaml

        return ["## the study config", "", "<details><summary>resolved config of the latest run</summary>", "",
                "```yaml", yaml.safe_dump(self.config, sort_keys=False).rstrip(), "```", "", "</details>", ""]


def provenance(rows: dict[str, dict], rows_dir: Path, runs: str | Path, command: str | None) -> Provenance:
    """The provenance of a report of ``rows`` (read from ``rows_dir``, the output ``runs``), made by
    ``command`` (default ``radarpc report RUNS``)."""
    def ranked(values):
        counts: dict = defaultdict(int)
        for v in values:
            counts[v] += 1
        return sorted(counts, key=lambda v: (-counts[v], str(v)))

    commands = ranked(r.get("command") or "(not recorded: the library was called directly)" for r in rows.values())
    files = ranked(r["study"].get("config_file") or "(not recorded)" for r in rows.values())
    commits = ranked((r.get("software") or {}).get("commit") or "unknown" for r in rows.values())
    # a row taken from another study (--reuse) is as recent as its taking, not its training
    latest = max(rows.values(), key=lambda r: max((r.get("times") or {}).get("finished_at") or "",
                                                  (r.get("times") or {}).get("reused_at") or ""))
    return Provenance(made_by=command or f"radarpc report {shlex.quote(str(runs))}", commands=commands, files=files,
                      commits=commits, config=latest["study"].get("config", {}),
                      own_commit=software_record().get("commit") or "unknown",
                      studies=sorted({f"{r['study']['name']} ({r['study']['kind']})" for r in rows.values()}),
                      n_rows=len(rows), rows_dir=Path(rows_dir))
