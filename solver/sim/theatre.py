"""A simulated operating theatre: the demo, the service benchmark and the end-to-end tests.

Everything is real except the patient and the C-arm: the service runs as it would in a
hospital (``slamtka serve`` on loopback, its own process), the C-arm's encoders are the
simulated device of ``drivers.carm_sim`` on a pseudo-terminal, its X-ray frames are rendered
from the built-in phantom (``solver.imaging.xray``) at the very poses the encoders report and
sent by C-STORE the moment the simulated C-arm exposes them, and the results arrive by
C-STORE at a destination SCP (:class:`ResultCollector`) standing in for the OR display.

Ground truth: the pins of each case are placed by ``solver.simulate`` (planned CTR/STR),
the patient lies a few degrees and millimetres off the nominal set-up the service assumes,
and every frame is rendered through the calibrated camera and its image-intensifier
distortion, so the service has to recover the true poses from the images.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import ssl
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
from pydicom.dataset import Dataset
from pydicom.uid import generate_uid
from pynetdicom import AE, evt
from pynetdicom.sop_class import (
    Comprehensive3DSRStorage,
    SecondaryCaptureImageStorage,
    Verification,
    XRayAngiographicImageStorage,
)

from slamtka.drivers.carm_sim import MotionScript, SimulatedCArm
from slamtka.drivers.kinematics import (
    CArmKinematics,
    JointReading,
    PatientSetup,
    dicom_angles,
    initial_view_poses,
)
from slamtka.service.cases import case_id_of, run_id_of
from slamtka.service.display import STATUS_SERIES
from slamtka.service.frames import Frame, encode_frame
from slamtka.service.plans import PlanStore
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.simulate import SimulationConfig, default_camera, simulate_case
from slamtka.sim.xray import XRayParams, XRayScene, default_distortion, render_radiograph
from slamtka.solver.geometry import Pose, rotation_about
from slamtka.solver.plan import Plan

__all__ = ["ResultCollector", "TheatreCase", "Theatre", "PATIENT_ID", "CARM_AE", "DISPLAY_AE"]

PATIENT_ID = "PHANTOM-R"
CARM_AE = "CARM_SIM"
DISPLAY_AE = "ORDISPLAY"
SERVICE_AE = "SLAMTKA"
SETUP_ROT_SD_DEG = 2.0  # how far the patient lies off the nominal set-up
SETUP_TRANS_SD_MM = 5.0


class ResultCollector:
    """A destination SCP on loopback (TLS with ``ssl_context``): keeps every result it
    receives, with its arrival time."""

    def __init__(self, ae_title: str = DISPLAY_AE, port: int = 0,
                 ssl_context: ssl.SSLContext | None = None, host: str = "127.0.0.1"):
        self.received: list[tuple[float, Dataset]] = []
        self._changed = threading.Condition()
        ae = AE(ae_title=ae_title)
        ae.require_called_aet = True
        for sop_class in (Comprehensive3DSRStorage, SecondaryCaptureImageStorage, Verification):
            ae.add_supported_context(sop_class)
        self._server = ae.start_server((host, port), block=False, ssl_context=ssl_context,
                                       evt_handlers=[(evt.EVT_C_STORE, self._store)])
        self.port = int(self._server.server_address[1])

    def _store(self, event) -> int:
        arrived = time.monotonic()
        ds = event.dataset
        ds.file_meta = event.file_meta
        with self._changed:
            self.received.append((arrived, ds))
            self._changed.notify_all()
        return 0x0000

    def wait(self, predicate, timeout: float, count: int = 1) -> list[tuple[float, Dataset]]:
        """Block until ``count`` received datasets satisfy ``predicate``; those received."""
        def matching() -> list[tuple[float, Dataset]]:
            return [(t, ds) for t, ds in self.received if predicate(ds)]

        with self._changed:
            self._changed.wait_for(lambda: len(matching()) >= count, timeout)
            return matching()

    def stop(self) -> None:
        self._server.shutdown()


@dataclass
class TheatreCase:
    """One simulated surgery: the truth and the rendered frames (not yet time-stamped)."""

    index: int
    study_uid: str
    truth_ctr_deg: float
    truth_str_deg: float
    frames: list[Frame]
    outlines: list[dict[str, np.ndarray]]  # true outlines per view, raw pixels (the truth)
    send_started: list[float] = field(default_factory=list)  # monotonic, before each C-STORE
    truth_T_tibia_pin: list = field(default_factory=list)  # the pins as placed (Pose)
    setup: PatientSetup | None = None  # how the patient really lies


def _evidence(sr: Dataset) -> set[str]:
    """The SOP Instance UIDs an SR names as its evidence."""
    return {item.ReferencedSOPInstanceUID
            for study in sr.get("CurrentRequestedProcedureEvidenceSequence", [])
            for series in study.ReferencedSeriesSequence
            for item in series.ReferencedSOPSequence}


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Theatre:
    """The service, a simulated C-arm and an OR display on loopback, in ``root``."""

    def __init__(self, root: Path, views_deg: tuple[float, ...] = (-30.0, 30.0), *,
                 encoders: bool = True, hold_s: float = 1.0, move_s: float = 1.8, seed: int = 1):
        self.root = Path(root)
        self.views_deg, self.encoders, self.seed = tuple(views_deg), encoders, seed
        self.script = MotionScript.from_orbital(self.views_deg, hold_s, move_s)
        self.kinematics = CArmKinematics()
        self.camera = default_camera()
        self.distortion = default_distortion(self.camera)
        self.plan: Plan | None = None
        self.carm: SimulatedCArm | None = None
        self.display: ResultCollector | None = None
        self.service: subprocess.Popen | None = None
        self.config: Path | None = None
        self.port = 0
        self.environ: dict[str, str] = {}  # configuration overrides (SLAMTKA_...) for the service
        self.clock_offset_s = 0.0  # how far the C-arm's frame times are off the host's clock
        self._scene: XRayScene | None = None

    # -- set-up ---------------------------------------------------------------------------
    def prepare(self) -> Path:
        """Plans folder (the phantom, precomputed once), calibration and configuration."""
        from slamtka.solver.imaging.calibration_file import write_calibration

        self.root.mkdir(parents=True, exist_ok=True)
        store = PlanStore(self.root / "plans")
        if not store.folder(PATIENT_ID, "right").is_dir():
            # Precomputing the phantom plan's distance fields takes seconds: keep a copy in the
            # user's cache and start every theatre from it.
            cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "slamtka"
            template = PlanStore(cache / "theatre-plans")
            if not template.folder(PATIENT_ID, "right").is_dir():
                phantom = phantom_plan("right")
                phantom.patient_id = PATIENT_ID
                template.add(phantom, {"landmarks": "given", "imported": "simulated theatre"})
            shutil.copytree(template.folder(PATIENT_ID, "right"), store.folder(PATIENT_ID, "right"))
        self.plan = store.find(PATIENT_ID, "R")
        self._scene = XRayScene.from_plan(self.plan, XRayParams(distortion=self.distortion))
        write_calibration(self.root / "carm-calibration.json", self.camera, self.distortion,
                          "simulated C-arm")
        return self.root / "carm-calibration.json"

    def write_config(self, display_port: int, encoder_port: str) -> Path:
        self.port = _free_port()
        path = self.root / "slamtka.toml"
        path.write_text(f"""# written by the simulated theatre
data_dir = "data"
plans_dir = "plans"
institution = "Simulated Theatre"

[dicom]
ae_title = "{SERVICE_AE}"
bind_address = "127.0.0.1"
port = {self.port}
allowed_calling_ae_titles = ["{CARM_AE}"]

[carm]
calibration = "carm-calibration.json"
encoder_port = "{encoder_port}"

[carm.link]
history_s = 900.0  # the benchmark's burst re-sends frames exposed minutes earlier

[pipeline]
manual_contours_dir = "contours"

[sender]
retry_initial_s = 0.5

[health]
http_port = 0  # any free port: theatres run side by side

[retention]
min_free_mb = 0  # benches run theatres on small file systems on purpose (a full disk)

[[destinations]]
name = "or-display"
ae_title = "{DISPLAY_AE}"
host = "127.0.0.1"
port = {display_port}
""")
        return path

    # -- cases ----------------------------------------------------------------------------
    def _true_setup(self, rng: np.random.Generator) -> PatientSetup:
        """The patient as they really lie: off the nominal set-up by a small rigid motion."""
        nominal = PatientSetup(self.plan.landmarks.T_tibia_anat())
        R = rotation_about(rng.normal(size=3), np.radians(rng.normal(0.0, SETUP_ROT_SD_DEG)))
        return PatientSetup(nominal.T_tibia_anat, tuple(R @ np.asarray(nominal.superior_carm)),
                            tuple(R @ np.asarray(nominal.anterior_carm)),
                            tuple(rng.normal(0.0, SETUP_TRANS_SD_MM, 3)))

    def make_case(self, index: int) -> TheatreCase:
        """Place the pins, render every view at its scripted C-arm position."""
        seed = self.seed * 1000 + index
        rng = np.random.default_rng(seed)
        sim = simulate_case(self.plan, SimulationConfig(view_angles_deg=(0.0,), seed=seed))
        setup = self._true_setup(rng)
        return self._render(index, generate_uid(prefix=None), list(sim.truth_T_tibia_pin), setup,
                            rng, sim.truth_ctr_deg, sim.truth_str_deg)

    def repin(self, case: TheatreCase, axis: str, angle_deg: float) -> TheatreCase:
        """The surgeon moves the pins: both turned by ``angle_deg`` about the anatomical
        ``axis`` ("ml": medio-lateral, changes STR; "ap": antero-posterior, changes CTR)
        through their midpoint; new views of the same study, the patient lying as before."""
        from slamtka.solver.measurement import fit_resection_plane

        lm = self.plan.landmarks
        T_tibia_anat = lm.T_tibia_anat()
        direction = T_tibia_anat.R @ {"ml": np.array([1.0, 0.0, 0.0]),
                                      "ap": np.array([0.0, 1.0, 0.0])}[axis]
        half = 0.5 * self.plan.pin_length()
        centre = np.mean([T.apply(np.array([0.0, 0.0, half])) for T in case.truth_T_tibia_pin], 0)
        R = rotation_about(direction, np.radians(angle_deg))
        turn = Pose(R, centre - R @ centre)
        pins = [turn @ T for T in case.truth_T_tibia_pin]
        plane = fit_resection_plane(pins, self.plan.pin_length(), lm)
        rng = np.random.default_rng([self.seed, case.index, int(round(angle_deg * 10)) + 1000,
                                     len(axis) + ord(axis[0])])
        return self._render(case.index, case.study_uid, pins, case.setup, rng,
                            float(np.degrees(plane.ctr)), float(np.degrees(plane.str_)))

    def _render(self, index: int, study: str, pins: list, setup: PatientSetup,
                rng: np.random.Generator, ctr_deg: float, str_deg: float) -> TheatreCase:
        """Render every scripted view of pins ``pins`` with the patient lying as ``setup``."""
        nominal = PatientSetup(self.plan.landmarks.T_tibia_anat())
        series = generate_uid(prefix=None)
        frames, outlines = [], []
        for k, joints in enumerate(self.script.views, start=1):
            (T_cam_tibia,), _ = initial_view_poses(self.kinematics, [joints], setup)
            image = render_radiograph(self.plan, T_cam_tibia, pins, self.camera,
                                      XRayParams(distortion=self.distortion), rng, self._scene)
            primary, secondary = dicom_angles(self.kinematics, joints, nominal)
            spacing = self._pixel_spacing_mm(joints)
            frames.append(Frame(
                pixels=image.image, sop_instance_uid=generate_uid(prefix=None), imager_pixel_spacing_mm=(spacing, spacing),
                primary_angle_deg=round(primary, 1), secondary_angle_deg=round(secondary, 1),
                sid_mm=self.kinematics.sid(joints), sod_mm=self.kinematics.source_to_isocentre_mm,
                patient_id=PATIENT_ID, patient_name="Phantom^Right", study_uid=study,
                series_uid=series, laterality="R", bits_stored=image.bits_stored,
                instance_number=k))
            outlines.append(image.silhouettes)
        return TheatreCase(index, study, ctr_deg, str_deg, frames, outlines,
                           truth_T_tibia_pin=pins, setup=setup)

    def _pixel_spacing_mm(self, joints: JointReading) -> float:
        """Detector pixel size: the calibrated focal length is SID over the pixel pitch."""
        return self.kinematics.sid(joints) / self.camera.fx

    # -- running --------------------------------------------------------------------------
    def start(self) -> None:
        self.display = ResultCollector()
        encoder_port = ""
        if self.encoders:
            self.carm = SimulatedCArm(self.script).start()
            encoder_port = self.carm.port
        self.config = self.write_config(self.display.port, encoder_port)
        self.start_service()

    def start_service(self) -> None:
        """(Re)start ``slamtka serve`` with this theatre's configuration."""
        with open(self.root / "service.log", "ab") as log:
            self.service = subprocess.Popen(
                [sys.executable, "-m", "slamtka.service.cli", "serve", "--config", str(self.config)],
                stdout=log, stderr=subprocess.STDOUT, cwd=self.root,  # as deployed: not in a checkout
                env={**os.environ, "PYTHONUNBUFFERED": "1", **self.environ})
        self._wait_for_service(60.0)

    def stop_service(self, kill: bool = False) -> int:
        """SIGTERM (a clean stop) or SIGKILL (a crash); the exit status."""
        if kill:
            self.service.kill()
        else:
            self.service.terminate()
        return self.service.wait(timeout=60)

    def _wait_for_service(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        ae = AE(ae_title=CARM_AE)
        ae.add_requested_context(Verification)
        while time.monotonic() < deadline:
            if self.service.poll() is not None:
                raise RuntimeError(f"the service exited with {self.service.returncode}; see "
                                   f"{self.root / 'service.log'}")
            try:  # the port first, so that the C-ECHO below is not logged as a failure
                socket.create_connection(("127.0.0.1", self.port), timeout=1.0).close()
            except OSError:
                time.sleep(0.2)
                continue
            assoc = ae.associate("127.0.0.1", self.port, ae_title=SERVICE_AE)
            if assoc.is_established:
                assoc.release()
                return
        raise RuntimeError("the service did not answer C-ECHO in time")

    def exposure_time(self, view: int, after: float) -> float:
        """The next monotonic time, not before ``after``, at which the C-arm exposes ``view``."""
        s = self.script
        cycle = len(s.views) * (s.hold_s + s.move_s)
        offset = view * (s.hold_s + s.move_s) + s.hold_s / 2
        boot = self.carm.boot_monotonic if self.carm is not None else 0.0
        n = np.ceil((after - boot - offset) / cycle)
        return boot + max(n, 0) * cycle + offset

    def acquire(self, case: TheatreCase, keep_times: bool = False,
                views: list[int] | None = None) -> None:
        """Expose and send each view of ``case`` when the simulated C-arm holds at it
        (``keep_times``: send at once, with the acquisition times the frames already carry;
        ``views``: the script's view each frame shows, default the frames' order)."""
        ae = AE(ae_title=CARM_AE)
        ae.add_requested_context(XRayAngiographicImageStorage)
        after = time.monotonic()
        for k, frame in enumerate(case.frames):
            if not keep_times:
                if self.encoders:
                    view = k if views is None else views[k]
                    time.sleep(max(0.0, self.exposure_time(view, after) - time.monotonic()))
                frame.acquisition_datetime = datetime.now(UTC) + timedelta(
                    seconds=self.clock_offset_s)
            ds = encode_frame(frame)
            case.send_started.append(time.monotonic())
            assoc = ae.associate("127.0.0.1", self.port, ae_title=SERVICE_AE)
            if not assoc.is_established:
                raise RuntimeError("the service refused the C-arm's association")
            status = assoc.send_c_store(ds)
            assoc.release()
            if getattr(status, "Status", None) != 0x0000:
                raise RuntimeError(f"the service refused a frame: {status}")
            after = time.monotonic()

    @staticmethod
    def replay_case(case: TheatreCase) -> TheatreCase:
        """The same exposures as a new study (new UIDs, same pixels and acquisition times)."""
        study, series = generate_uid(prefix=None), generate_uid(prefix=None)
        frames = [replace(f, study_uid=study, series_uid=series,
                          sop_instance_uid=generate_uid(prefix=None)) for f in case.frames]
        return TheatreCase(case.index, study, case.truth_ctr_deg, case.truth_str_deg, frames,
                           case.outlines, truth_T_tibia_pin=case.truth_T_tibia_pin,
                           setup=case.setup)

    def result_folder(self, case: TheatreCase) -> Path:
        """Where the service writes the run of all of ``case``'s views."""
        run = run_id_of([f.sop_instance_uid for f in case.frames])
        return self.root / "data" / "output" / case_id_of(PATIENT_ID, case.study_uid, "R") / run

    def wait_for_result(self, case: TheatreCase, timeout: float = 120.0,
                        exact: bool = False) -> tuple[float, Dataset]:
        """(arrival time, SR) of the case's measurement report at the OR display (status
        reports aside); ``exact``: the report of a run of exactly ``case``'s frames."""
        sops = {f.sop_instance_uid for f in case.frames} if exact else set()
        items = self.display.wait(lambda ds: ds.StudyInstanceUID == case.study_uid
                                  and ds.Modality == "SR" and ds.SeriesDescription != STATUS_SERIES
                                  and (not sops or _evidence(ds) == sops), timeout)
        if not items:
            raise TimeoutError(f"no result for case {case.index} within {timeout:.0f} s")
        return items[0]

    def stop(self) -> None:
        if self.service is not None and self.service.poll() is None:
            self.service.terminate()
            try:
                self.service.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.service.kill()
        if self.carm is not None:
            self.carm.stop()
        if self.display is not None:
            self.display.stop()


# -- `slamtka theatre`: the end-to-end demonstration ------------------------------------------

def _print_result(doc: dict, case: TheatreCase) -> None:
    print(f"\nresult {doc['case_id']}: {doc['status'].replace('_', ' ')}")
    if doc["angles"] is None:
        print(f"  reason: {doc['reason']}")
    else:
        a, t = doc["angles"], doc["target"]
        print(f"  CTR {a['ctr_deg']:+6.2f} deg +- {a['ctr_sigma_deg']:.2f}   (simulated truth "
              f"{case.truth_ctr_deg:+.2f}; plan {t['ctr_deg']:+.1f})   positive = varus")
        print(f"  STR {a['str_deg']:+6.2f} deg +- {a['str_sigma_deg']:.2f}   (simulated truth "
              f"{case.truth_str_deg:+.2f}; plan {t['str_deg']:+.1f})   positive = posterior slope")
        print(f"  verdict: {doc['verdict']} (tolerance +-{t['tolerance_deg']:.1f} deg)")
    for s in doc["sources"]:
        print(f"  {s['view_id']}: initialised from {s['initialisation']}, contours {s['contours']}")
    print(f"  pipeline {doc['timings']['total_s']:.2f} s (solve {doc['timings'].get('solve_s', 0):.2f} s)")


def parse_angles(text: str) -> tuple[float, ...]:
    """``"-30,30"`` -> (-30.0, 30.0), for the command line."""
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def cmd_theatre(args: argparse.Namespace) -> int:
    root = args.out or Path(tempfile.mkdtemp(prefix="slamtka-theatre-"))
    theatre = Theatre(root, args.views, encoders=not args.no_encoders, seed=args.seed)
    print(f"simulated theatre in {root}: slamtka serve on loopback, a C-arm with encoders on a "
          f"pseudo-terminal, {len(args.views)} views of the built-in phantom over DICOM")
    theatre.prepare()
    case = theatre.make_case(0)
    theatre.start()
    try:
        print(f"service up on 127.0.0.1:{theatre.port} (AE {SERVICE_AE}); encoder link on "
              f"{theatre.carm.port if theatre.carm else 'none (positioner angles)'}")
        theatre.acquire(case)
        for frame in case.frames:
            print(f"  exposed and sent view at primary {frame.primary_angle_deg:+.1f} deg, "
                  f"{frame.acquisition_datetime:%H:%M:%S.%f}"[:-3])
        arrived, _ = theatre.wait_for_result(case)
        print(f"structured report at the OR display {arrived - case.send_started[-1]:.2f} s after "
              "the last view was sent")
        folder = theatre.result_folder(case)
        deadline = time.monotonic() + 30.0
        while not (folder / "result.json").is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        doc = json.loads((folder / "result.json").read_text())
    finally:
        theatre.stop()
    _print_result(doc, case)
    print("\noutputs:")
    for name in ["result.json", "recording.rrd", "sr.dcm"] + sorted(
            p.name for p in folder.glob("sc-*.dcm")):
        print(f"  {folder / name}")
    print(f"  audit log: {root / 'data' / 'audit.jsonl'}")
    print(f"\nreplay the audit recording: slamtka replay {folder / 'recording.rrd'} "
          f"--check {folder / 'result.json'}")
    return 0 if doc["status"] == "measured" else 3


def add_theatre_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("theatre", help="end-to-end demo: the service, a simulated C-arm, the phantom")
    p.add_argument("--out", type=Path, help="working folder (default: a new temporary folder)")
    p.add_argument("--views", type=parse_angles, default=(-30.0, 30.0),
                   help="orbital angles of the views, deg")
    p.add_argument("--no-encoders", action="store_true", help="no encoder link")
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(func=cmd_theatre)
