"""Retention: an unattended install never fills its disk, and starts as fast on its thousandth
case as on its first.

A case idle for ``archive_after_hours`` (a surgery day) whose results have all been delivered
is *archived*: its spooled instances and sidecars move to ``spool/archive/<case>/``, out of
what a restart replays, so start-up reads only the frames of recent cases. An archived case
whose newest file is older than ``keep_days`` is *pruned*: its archive, its results
(``output/<case>/``) and its pin sets go. A result still waiting in the send queue keeps its
case, whatever its age. Below ``min_free_mb`` of free disk the receiver refuses new storage
associations, with the reason, before the disk fills. Every archive and prune is audited;
``slamtka prune`` does the same by hand (the service does it every ``interval_s``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from slamtka.service.config import RetentionConfig

__all__ = ["Retention", "Sweep", "pending_case_ids", "add_prune_parser"]

_DAY_S = 86400.0


@dataclass
class Sweep:
    """What one pass did (or, dry, would do)."""

    archived: list[str] = field(default_factory=list)
    pruned: list[str] = field(default_factory=list)
    kept_undelivered: list[str] = field(default_factory=list)
    freed_bytes: int = 0


def pending_case_ids(queue_dir: Path) -> set[str]:
    """Cases with a result still in the send queue (read from the queue's job files)."""
    ids = set()
    for path in (Path(queue_dir) / "pending").glob("*.json"):
        try:
            ids.add(str(json.loads(path.read_text())["case_id"]))
        except (OSError, ValueError, KeyError):
            continue  # a job being written or damaged: the sender names it; nothing is pruned for it
    return ids


def _newest_mtime(paths: Iterable[Path]) -> float:
    return max((p.stat().st_mtime for p in paths if p.exists()), default=0.0)


def _tree_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


class Retention:
    """Archiving and pruning of one data folder, and the disk floor."""

    def __init__(self, config: RetentionConfig, data_dir: Path, output_dir: Path,
                 audit: Callable[..., object] | None = None):
        self.config = config
        self.data_dir, self.output_dir = Path(data_dir), Path(output_dir)
        self.spool_dir = self.data_dir / "spool"
        self.archive_dir = self.spool_dir / "archive"
        self.audit = audit

    # -- the disk floor ----------------------------------------------------------------------
    def space_problem(self) -> str | None:
        """Why no new frame may be received now (None when there is room)."""
        free_mb = shutil.disk_usage(self.data_dir).free / 1e6
        if free_mb >= self.config.min_free_mb:
            return None
        return (f"disk nearly full: {free_mb:.0f} MB free under {self.data_dir}, below the floor "
                f"of {self.config.min_free_mb:.0f} MB (retention.min_free_mb); free space or "
                "run `slamtka prune`")

    # -- archiving (the service's live cases) --------------------------------------------------
    def idle_cases(self, cases: dict[str, list[Path]], pending: set[str],
                   now: float | None = None) -> list[str]:
        """Of ``cases`` (case id -> its instance files), those idle long enough to archive."""
        now = time.time() if now is None else now
        limit = now - self.config.archive_after_hours * 3600.0
        return [case_id for case_id, files in cases.items()
                if case_id not in pending and _newest_mtime(files) < limit]

    def archive(self, case_id: str, files: list[Path], dry_run: bool = False) -> None:
        """Move a case's instances and sidecars out of what start-up replays."""
        if dry_run:
            return
        folder = self.archive_dir / case_id
        folder.mkdir(parents=True, exist_ok=True)
        for path in files:
            for item in (path, path.with_suffix(".json")):
                if item.exists():
                    item.replace(folder / item.name)
        if self.audit is not None:
            self.audit("case_archived", case_id=case_id, instances=len(files))

    # -- pruning ---------------------------------------------------------------------------
    def prune(self, pending: set[str], active: frozenset[str] | set[str] = frozenset(), now: float | None = None,
              dry_run: bool = False) -> Sweep:
        """Delete the archives and results of cases older than ``keep_days``; never a case
        with a result in the send queue, nor one still live (``active``)."""
        now = time.time() if now is None else now
        limit = now - self.config.keep_days * _DAY_S
        sweep = Sweep()
        candidates = {p.name for root in (self.archive_dir, self.output_dir) if root.is_dir()
                      for p in root.iterdir() if p.is_dir() and p.name.startswith("case-")}
        for case_id in sorted(candidates - set(active)):
            folders = [f for f in (self.archive_dir / case_id, self.output_dir / case_id) if f.is_dir()]
            # A case's age: its frames' receipt and its results (a sidecar rewritten when the
            # spool is replayed at a start is no new activity).
            dated = [*(self.archive_dir / case_id).glob("*.dcm"), *(self.output_dir / case_id).rglob("*")]
            if _newest_mtime(p for p in dated if p.is_file()) >= limit:
                continue
            if case_id in pending:
                sweep.kept_undelivered.append(case_id)
                continue
            size = sum(_tree_bytes(f) for f in folders)
            if not dry_run:
                for folder in folders:
                    shutil.rmtree(folder)
                (self.data_dir / "pinsets" / f"{case_id}.json").unlink(missing_ok=True)
                if self.audit is not None:
                    self.audit("case_pruned", case_id=case_id, bytes=size,
                               older_than_days=self.config.keep_days)
            sweep.pruned.append(case_id)
            sweep.freed_bytes += size
        return sweep


# -- `slamtka prune`: the same, by hand, with the service stopped ------------------------------

def _live_cases(instances: Path) -> dict[str, list[Path]]:
    """Instance files of the live spool by case (read from their headers)."""
    import pydicom

    from slamtka.service.cases import case_id_of
    from slamtka.service.frames import case_key

    cases: dict[str, list[Path]] = {}
    for path in sorted(instances.glob("*.dcm")):
        try:
            case_id = case_id_of(*case_key(pydicom.dcmread(path, stop_before_pixels=True)))
        except Exception:  # a damaged file is the service's to quarantine at its next start
            continue
        cases.setdefault(case_id, []).append(path)
    return cases


def cmd_prune(args: argparse.Namespace) -> int:
    from slamtka.service.audit import AuditLog
    from slamtka.service.config import load_config
    from slamtka.service.serve import DataFolderBusy, lock_data_folder

    config = load_config(args.config)
    try:
        lock = lock_data_folder(config.data_dir)
    except DataFolderBusy as exc:
        raise RuntimeError(f"{exc}: the service archives and prunes by itself every "
                           f"{config.retention.interval_s:.0f} s (retention.interval_s)") from None
    audit = None if args.dry_run else AuditLog(config.audit_log)
    try:
        retention = Retention(config.retention, config.data_dir, config.output,
                              None if audit is None else audit.record)
        pending = pending_case_ids(config.queue_dir)
        live = _live_cases(config.spool_dir / "instances")
        idle = retention.idle_cases(live, pending)
        for case_id in idle:
            retention.archive(case_id, live[case_id], dry_run=args.dry_run)
        sweep = retention.prune(pending, active=set(live) - set(idle), dry_run=args.dry_run)
    finally:
        if audit is not None:
            audit.close()
        os.close(lock)
    verb = "would be" if args.dry_run else "were"
    print(f"{len(idle)} idle case(s) {verb} archived; {len(sweep.pruned)} case(s) older than "
          f"{config.retention.keep_days:g} days {verb} deleted ({sweep.freed_bytes / 1e6:.1f} MB); "
          f"{len(sweep.kept_undelivered)} kept: a result still waits in the send queue")
    return 0


def add_prune_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("prune", help="archive idle cases and delete old ones (retention policy)")
    p.add_argument("--config", type=Path, required=True)
    p.add_argument("--dry-run", action="store_true", help="say what would go; change nothing")
    p.set_defaults(func=cmd_prune)
