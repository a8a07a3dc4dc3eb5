"""Calibrations per C-arm: which calibration a received frame is measured with.

Each C-arm, and each detector field (intensifier size / zoom) of it, has its own
calibration. Installed calibrations live in ``data_dir/calibrations/<id>.json``
(``slamtka calibration install``), each bound to the C-arm it was made for by one identity:
its Device Serial Number (0018,1000), its Station Name (0008,1010) or the calling AE title it
sends with (kept by the receiver as the file's Source Application Entity Title, 0002,0016);
``carm.calibration_match`` says which. A frame is measured with the installed calibration of
its C-arm whose detector matches the frame (size, pixel spacing, field size when both say);
a C-arm with no installed calibration falls back to ``carm.calibration`` (the single
calibration of a one-C-arm site) if that is set, and is refused, with the reason, if not.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import threading
from collections import Counter
from collections.abc import Callable
from pathlib import Path

from pydicom.dataset import Dataset
from pydicom.multival import MultiValue

from slamtka.service.atomic_files import write_json_atomic
from slamtka.solver.imaging.calibration_file import (
    Calibration,
    CalibrationError,
    assign_device,
    load_calibration,
)

__all__ = ["DEVICE_KEYS", "CalibrationSet", "CalibrationStore", "device_identity",
           "detector_field_mm", "add_calibration_parser"]

# Identity key -> (what it is called for people, DICOM keyword; None: the file meta's
# Source Application Entity Title, which the receiver sets to the calling AE title).
DEVICE_KEYS = {"device_serial_number": ("Device Serial Number", "DeviceSerialNumber"),
               "station_name": ("Station Name", "StationName"),
               "calling_ae_title": ("calling AE title", None)}
_FIELD_TOLERANCE_MM = 0.5
log = logging.getLogger("slamtka.service")
_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,79}$")


def _text(value) -> str:
    return str(value or "").strip()


def device_identity(ds: Dataset) -> dict[str, str]:
    """The identities of the C-arm that sent (or wrote) an instance, as far as it says."""
    out = {}
    for key, (_, keyword) in DEVICE_KEYS.items():
        if keyword is None:
            meta = getattr(ds, "file_meta", None)
            value = _text(meta.get("SourceApplicationEntityTitle") if meta is not None else None)
        else:
            value = _text(ds.get(keyword))
        if value:
            out[key] = value
    return out


def detector_field_mm(ds: Dataset) -> float | None:
    """The detector field an instance was taken with: Intensifier Size, else the first of
    the Field of View Dimensions (mm); None when it says neither (or nonsense)."""
    for keyword in ("IntensifierSize", "FieldOfViewDimensions"):
        try:
            value = ds.get(keyword)
            if value is None or value == "":
                continue
            number = float(value[0] if isinstance(value, MultiValue) else value)
        except (TypeError, ValueError, IndexError):
            continue
        if 1.0 <= number <= 1000.0:
            return number
    return None


def _detector(calibration: Calibration) -> str:
    spacing = calibration.pixel_spacing_mm
    field = calibration.field_mm
    return (f"{calibration.camera.width}x{calibration.camera.height} px"
            + (f", {spacing[0]:.4g} mm pixels" if spacing else "")
            + (f", {field:g} mm field" if field else ""))


class CalibrationStore:
    """The folder of installed calibrations (``data_dir/calibrations``)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    def installed(self) -> list[Calibration]:
        """Every installed calibration, by id; a damaged file is refused naming it."""
        if not self.folder.is_dir():
            return []
        return [load_calibration(path) for path in sorted(self.folder.glob("*.json"))]

    def find(self, calibration_id: str) -> Calibration:
        for calibration in self.installed():
            if calibration.calibration_id == calibration_id:
                return calibration
        raise ValueError(f"no installed calibration {calibration_id!r} in {self.folder}")

    def install(self, source: Path, match: str, identity: str | None = None,
                field_mm: float | None = None, replace: bool = False) -> tuple[Path, Calibration]:
        """Verify ``source`` and install it for one C-arm (its ``match`` identity: given, or
        the one the calibration was made with); refuses a second calibration of the same
        C-arm and detector unless ``replace``."""
        calibration = load_calibration(source)
        label = DEVICE_KEYS[match][0]
        document = calibration.document()
        if identity is not None or field_mm is not None:
            device = {**calibration.device, **({match: identity} if identity is not None else {})}
            document = assign_device(document, device, field_mm)
        owner = (document.get("device") or {}).get(match)
        if not owner:
            raise ValueError(f"{source}: the calibration names no {label} of its C-arm; give it "
                             f"(--{match.replace('_', '-')} VALUE)")
        if not _SAFE_ID.match(calibration.calibration_id):
            raise ValueError(f"{source}: calibration id {calibration.calibration_id!r} cannot name a "
                             "file (letters, digits, _ . - only)")
        target = self.folder / f"{calibration.calibration_id}.json"
        self.folder.mkdir(parents=True, exist_ok=True)
        staged = self.folder / f".{calibration.calibration_id}.staged"
        write_json_atomic(staged, document)
        try:
            candidate = load_calibration(staged)
        finally:
            staged.unlink(missing_ok=True)
        for other in self.installed():
            same_id = other.calibration_id == candidate.calibration_id
            same_slot = (other.device.get(match) == owner and _detector(other) == _detector(candidate))
            if (same_id or same_slot) and not replace:
                why = "the same id" if same_id else f"the same C-arm ({label} {owner!r}) and detector"
                raise ValueError(f"calibration {other.calibration_id} is installed for {why}; "
                                 "give --replace to replace it")
            if same_slot and not same_id:
                (self.folder / f"{other.calibration_id}.json").unlink()
        write_json_atomic(target, document)
        return target, load_calibration(target)


class CalibrationSet:
    """What the service measures with: the installed calibrations and the default.

    Loaded from a folder, the set follows it: a calibration installed, replaced or removed
    while the service runs is used from the next frame on, without a restart. A folder that
    no longer reads (a damaged file) leaves the set as it was, and ``on_change`` is told.
    """

    def __init__(self, installed: list[Calibration], default: Calibration | None,
                 match: str = "device_serial_number", folder: Path | None = None,
                 on_change: Callable[[str, dict], object] | None = None):
        if match not in DEVICE_KEYS:
            raise ValueError(f"calibration match {match!r} is not one of {sorted(DEVICE_KEYS)}")
        self.installed, self.default, self.match = installed, default, match
        self.folder, self.on_change = folder, on_change
        self._seen = _folder_state(folder)
        self._lock = threading.Lock()

    @classmethod
    def load(cls, folder: Path, default: Path | None, match: str,
             on_change: Callable[[str, dict], object] | None = None) -> CalibrationSet:
        """Read and verify every calibration (at start-up); none at all is refused."""
        installed = CalibrationStore(folder).installed()
        calibration = None if default is None else load_calibration(default)
        if not installed and calibration is None:
            raise CalibrationError(f"no calibration: set carm.calibration, or install one per C-arm "
                                   f"into {folder} with `slamtka calibration install`")
        return cls(installed, calibration, match, folder, on_change)

    def refresh(self) -> None:
        """Re-read the folder if a file in it was added, changed or removed since last read."""
        if self.folder is None:
            return
        with self._lock:
            state = _folder_state(self.folder)
            if state == self._seen:
                return
            self._seen = state
            before = {c.calibration_id: c.sha256 for c in self.installed}
            try:
                installed = CalibrationStore(self.folder).installed()
            except (CalibrationError, OSError, ValueError) as exc:
                self._tell("calibrations_unreadable", {
                    "folder": str(self.folder), "error": str(exc),
                    "kept": sorted(before)})
                return
            self.installed = installed
            after = {c.calibration_id: c.sha256 for c in installed}
            self._tell("calibrations_reloaded", {
                "added": sorted(set(after) - set(before)), "removed": sorted(set(before) - set(after)),
                "replaced": sorted(i for i in set(after) & set(before) if after[i] != before[i])})

    def _tell(self, event: str, fields: dict) -> None:
        """Tell ``on_change``; its failure (say, the audit log's disk full) must not keep a
        frame from its calibration."""
        if self.on_change is None:
            return
        try:
            self.on_change(event, fields)
        except Exception:
            log.exception("calibrations: cannot tell %s %s", event, fields)

    def select(self, header: Dataset, frame) -> tuple[Calibration | None, str | None]:
        """The calibration for a frame (``frame``: width, height, pixel spacing; ``header``:
        its DICOM attributes), or None and why there is none."""
        self.refresh()
        label = DEVICE_KEYS[self.match][0]
        identity = device_identity(header).get(self.match)
        mine = [c for c in self.installed if identity and c.device.get(self.match) == identity]
        if not mine:
            if self.default is not None:
                return self.default, None
            if not identity:
                return None, f"the frame names no {label}: its C-arm's calibration cannot be chosen"
            return None, (f"no calibration for the C-arm with {label} {identity!r} (install one with "
                          "`slamtka calibration install`)")
        field = detector_field_mm(header)
        fitting = [c for c in mine if c.check_frame(frame) is None and (
            c.field_mm is None or field is None or abs(c.field_mm - field) <= _FIELD_TOLERANCE_MM)]
        if not fitting:
            have = "; ".join(f"{c.calibration_id} ({_detector(c)})" for c in mine)
            spacing = frame.imager_pixel_spacing_mm
            return None, (f"the C-arm with {label} {identity!r} has no calibration for this detector "
                          f"field ({frame.width}x{frame.height} px, {spacing[0]:.4g} mm pixels"
                          + (f", {field:g} mm field" if field else "") + f"); it has: {have}")
        # A calibration made for this very field before one that does not say.
        fitting.sort(key=lambda c: c.field_mm is None)
        return fitting[0], None

    def describe(self) -> dict:
        """For the status board."""
        self.refresh()
        return {"match": self.match,
                "default": None if self.default is None else {
                    "id": self.default.calibration_id, "sha256": self.default.sha256},
                "installed": [{"id": c.calibration_id, "sha256": c.sha256, "device": c.device,
                               "detector": _detector(c)} for c in self.installed]}


def _folder_state(folder: Path | None) -> tuple[tuple[str, int, int], ...]:
    """What says the folder's calibrations changed: each file's name, size and change time."""
    if folder is None or not folder.is_dir():
        return ()
    state = []
    for path in folder.glob("*.json"):
        try:
            st = path.stat()
        except FileNotFoundError:  # removed while looked at: the next look sees it gone
            continue
        state.append((path.name, st.st_size, st.st_mtime_ns))
    return tuple(sorted(state))


def choose_for_run(selected: list[tuple[Calibration | None, str | None]]) -> Calibration | None:
    """The one calibration of a run: the one most of its views need (the latest on a tie)."""
    ids = [c.calibration_id for c, problem in selected if c is not None and problem is None]
    if not ids:
        return None
    counts = Counter(ids)
    best = max(counts.values())
    chosen = [i for i in ids if counts[i] == best][-1]
    return next(c for c, _ in selected if c is not None and c.calibration_id == chosen)


# -- slamtka calibration list | show | install ---------------------------------------------

def _store(args: argparse.Namespace):
    from slamtka.service.config import load_config

    config = load_config(args.config)
    return config, CalibrationStore(config.data_dir / "calibrations")


def cmd_calibration(args: argparse.Namespace) -> int:
    config, store = _store(args)
    match = config.carm.calibration_match
    if args.action == "install":
        path, calibration = store.install(args.file, match, getattr(args, match), args.field,
                                          args.replace)
        print(f"installed {calibration.calibration_id} for the C-arm with {DEVICE_KEYS[match][0]} "
              f"{calibration.device[match]!r} ({_detector(calibration)}) -> {path}")
        return 0
    installed = store.installed()
    default = config.carm.calibration
    if args.action == "list":
        print(f"calibrations in {store.folder} (chosen by {DEVICE_KEYS[match][0]}):")
        for c in installed:
            print(f"  {c.calibration_id}: {DEVICE_KEYS[match][0]} {c.device.get(match, '-')!r}, "
                  f"{_detector(c)}, RMS {c.document().get('rms_px', float('nan')):.3f} px, "
                  f"created {c.document().get('created', '?')}")
        if not installed:
            print("  (none)")
        print(f"default (carm.calibration, for C-arms without their own): {default or 'none'}")
        return 0
    calibration = (load_calibration(default) if args.id == "default" and default is not None
                   else store.find(args.id))
    print(json.dumps(calibration.document(), indent=2))
    return 0


def add_calibration_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibration", help="list, show or install the calibrations of the C-arms")
    actions = p.add_subparsers(dest="action", required=True)
    for name, text in (("list", "the installed calibrations"), ("show", "one calibration's file"),
                       ("install", "install a calibration file for a C-arm")):
        q = actions.add_parser(name, help=text)
        q.add_argument("--config", type=Path, required=True, help="service configuration (TOML)")
        if name == "show":
            q.add_argument("id", help="calibration id (or 'default')")
        if name == "install":
            q.add_argument("file", type=Path, help="calibration file from `slamtka calibrate`")
            for key, (label, _) in DEVICE_KEYS.items():
                q.add_argument(f"--{key.replace('_', '-')}", dest=key,
                               help=f"the C-arm's {label} (default: the one its frames named)")
            q.add_argument("--field", type=float, help="detector field (intensifier size) it is for, mm")
            q.add_argument("--replace", action="store_true",
                           help="replace the calibration of the same C-arm and detector")
        q.set_defaults(func=cmd_calibration)
