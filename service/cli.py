"""The ``slamtka`` command line.

Its own sub-commands: ``simulate`` (write a simulated case folder), ``solve`` (measure a case
folder), ``demo`` (simulate and solve the built-in phantom). The others are registered by the
modules that implement them: ``bench`` (accuracy, link, service, speed, degenerate, imaging,
hardening), ``calibrate``, ``calibration``, ``carm-sim``, ``plan``, ``status``, ``replay``, ``serve`` and
``theatre``; ``slamtka --help`` lists them.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

from drivers.carm_sim import add_carm_sim_parser
from solver.case import load_case, write_case
from solver.imaging.operating_room import NUISANCES, OperatingRoom, view_angles
from solver.jsonfile import read_json_object
from solver.plan import Plan
from solver.result import result_document
from solver.simulate import SimulationConfig, simulate_case
from solver.slam import METHODS, SolverConfig, solve_joint

from .bench import add_bench_parser
from .calibrate import add_calibrate_parser
from .calibrations import add_calibration_parser
from .sim_calibration import write_calibration_set
from .case_cli import add_case_parser
from .measure import add_measure_parser
from .sim_images import write_case_images
from .plans import add_plan_parser
from .replay import add_replay_parser
from .serve import add_serve_parser
from .status import add_status_parser
from .theatre import add_theatre_parser

log = logging.getLogger("slamtka")


def _floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _add_model_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tibia", type=Path, help="tibia mesh (STL/PLY/OBJ); default: built-in phantom")
    p.add_argument("--fibula", type=Path, help="fibula mesh (optional, with --tibia)")
    p.add_argument("--landmarks", type=Path, help="landmarks JSON (required with --tibia)")
    p.add_argument("--side", choices=("left", "right"), default="right")


def cmd_simulate(args: argparse.Namespace) -> int:
    if getattr(args, "calibration_images", None) is not None:
        paths = write_calibration_set(args.out, args.calibration_images, args.seed)
        print(f"wrote a simulated phantom set of {len(paths)} DICOM frames to {args.out} "
              f"(calibrate it with: slamtka calibrate {args.out}/*.dcm --out carm.json)")
        return 0
    if args.tibia is None:
        plan = Plan.phantom(args.side)
    elif args.landmarks is None:
        raise ValueError("--tibia needs --landmarks (knee centre, ankle centre, anterior, side)")
    else:
        plan = Plan.from_meshes(args.tibia, args.fibula, args.landmarks)
    if getattr(args, "patient_id", None):
        plan.patient_id = args.patient_id
    room = _operating_room(args)
    if room.names and room.names != ["views"] and not getattr(args, "images", False):
        raise ValueError("operating-room nuisances other than the views are in the frames: add --images")
    views = view_angles(room.draw(args.seed), args.views)
    config = SimulationConfig(view_angles_deg=views, noise_px=args.noise_px, seed=args.seed,
                              init_rot_sd_rad=args.init_rot_sd, init_trans_sd_mm=args.init_trans_sd)
    case = simulate_case(plan, config)
    truth = {
        "ctr_deg": case.truth_ctr_deg,
        "str_deg": case.truth_str_deg,
        "T_cam_tibia": {v.view_id: T.to_json() for v, T in zip(case.views, case.truth_T_cam_tibia)},
        "T_tibia_pin": [T.to_json() for T in case.truth_T_tibia_pin],
        "simulation": {"seed": args.seed, "noise_px": args.noise_px, "views_deg": list(views),
                       "nuisances": room.names,
                       "init_rot_sd_rad": args.init_rot_sd, "init_trans_sd_mm": args.init_trans_sd},
    }
    write_case(args.out, f"sim-{args.seed}", plan, case.views, case.initial, "simulated-carm",
               truth)
    if getattr(args, "images", False):
        write_case_images(args.out, plan, case, "simulated-carm", args.seed, room=room,
                          patient_name=getattr(args, "patient_name", None))
    print(f"wrote simulated case to {args.out} (true CTR {case.truth_ctr_deg:+.2f} deg, "
          f"STR {case.truth_str_deg:+.2f} deg)")
    return 0


def _operating_room(args: argparse.Namespace) -> OperatingRoom:
    """The scene ``--scene`` names, with every nuisance flag given added to it."""
    meshes = getattr(args, "nuisance_meshes", None)
    base = (OperatingRoom.everything(meshes) if getattr(args, "scene", "idealised") == "operating-room"
            else OperatingRoom(mesh_folder=meshes))
    return replace(base, **{name: True for name in NUISANCES if getattr(args, name, False)})


def _summary(doc: dict) -> str:
    lines = [f"case {doc['case_id']}: {doc['status'].replace('_', ' ')}"]
    if doc["angles"] is None:
        lines.append(f"  reason: {doc['reason']}")
    else:
        a, d, t = doc["angles"], doc["deviation"], doc["target"]
        lines += [
            f"  CTR {a['ctr_deg']:+6.2f} deg +- {a['ctr_sigma_deg']:.2f}  (plan {t['ctr_deg']:+.1f}, "
            f"deviation {d['ctr_deg']:+.2f})   positive = varus",
            f"  STR {a['str_deg']:+6.2f} deg +- {a['str_sigma_deg']:.2f}  (plan {t['str_deg']:+.1f}, "
            f"deviation {d['str_deg']:+.2f})   positive = posterior slope",
            f"  within +-{t['tolerance_deg']:.1f} deg of plan: {'yes' if d['within_tolerance'] else 'NO'}",
        ]
    s = doc["solver"]
    rms = ", ".join(f"{k} {v:.2f}" for k, v in s["residual_rms_sigma"].items())
    lines.append(f"  solver ({s['method']}, started from the {s['start']}): {s['iterations']} "
                 f"iterations, {s['seconds']:.2f} s, {s['convergence_reason']}; residual RMS "
                 f"(sigmas): {rms or 'n/a'}")
    return "\n".join(lines)


def _truth_line(folder: Path, doc: dict) -> str | None:
    path = folder / "ground_truth.json"
    if not path.is_file() or doc["angles"] is None:
        return None
    truth = read_json_object(path)
    e_ctr = doc["angles"]["ctr_deg"] - truth["ctr_deg"]
    e_str = doc["angles"]["str_deg"] - truth["str_deg"]
    return (f"  simulated truth: CTR {truth['ctr_deg']:+.2f}, STR {truth['str_deg']:+.2f} deg; "
            f"error CTR {e_ctr:+.3f}, STR {e_str:+.3f} deg")


def cmd_solve(args: argparse.Namespace) -> int:
    case = load_case(args.case_dir)
    outcome = solve_joint(case.plan, case.views, case.initial, SolverConfig(method=args.method))
    doc = result_document(case.case_id, outcome, case.plan, case.views, case.calibration_id,
                          args.method)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2))
    print(_summary(doc))
    truth = _truth_line(args.case_dir, doc)
    if truth:
        print(truth)
    return 0 if doc["status"] == "measured" else 3


def cmd_demo(args: argparse.Namespace) -> int:
    folder = args.out or Path(tempfile.mkdtemp(prefix="slamtka-demo-"))
    print("slamtka demo: simulate two C-arm views of the built-in phantom, then measure")
    sim = argparse.Namespace(tibia=None, fibula=None, landmarks=None, side="right", views=(-30.0, 30.0),
                             noise_px=2.0, seed=args.seed, init_rot_sd=0.1, init_trans_sd=20.0,
                             out=folder)
    cmd_simulate(sim)
    return cmd_solve(argparse.Namespace(case_dir=folder, json=folder / "result.json", method="slam"))


def _shared_meshes() -> Path | None:
    """The shared nuisance meshes beside the repository, when there (the simulator's only)."""
    folder = Path(__file__).resolve().parents[2] / "shared" / "data" / "knee-nuisance"
    return folder if folder.is_dir() else None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slamtka", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="write a simulated case folder")
    p.add_argument("--out", type=Path, required=True)
    _add_model_options(p)
    p.add_argument("--views", type=_floats, default=(-30.0, 30.0),
                   help="view angles about the leg axis, degrees (0 = AP)")
    p.add_argument("--noise-px", type=float, default=2.0)
    p.add_argument("--init-rot-sd", type=float, default=0.1, help="initial rotation error SD, rad")
    p.add_argument("--init-trans-sd", type=float, default=20.0, help="initial translation error SD, mm")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--images", action="store_true",
                   help="also render the views as DICOM X-ray frames with their true outlines")
    p.add_argument("--calibration-images", type=int, metavar="N",
                   help="instead of a case, write N phantom frames of the simulated C-arm (plus an "
                        "empty frame and a duplicate) for `slamtka calibrate`")
    p.add_argument("--scene", choices=("idealised", "operating-room"), default="idealised",
                   help="idealised frames, or every operating-room nuisance at once")
    for name in NUISANCES:
        flag = "surgeon-views" if name == "views" else name.replace("_", "-")  # --views is taken
        p.add_argument(f"--{flag}", dest=name, action="store_true",
                       help=f"add the {name.replace('_', ' ')} nuisance (solver/imaging/operating_room.py)")
    p.add_argument("--nuisance-meshes", type=Path, default=_shared_meshes(),
                   help="folder with femur-generic-right.stl and patella-right.stl (metres)")
    p.add_argument("--patient-id", help="Patient ID of the plan and the frames (default: the plan's)")
    p.add_argument("--patient-name", help="Patient's Name in the frames (default: the Patient ID)")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("solve", help="measure the resection plane of a case folder")
    p.add_argument("case_dir", type=Path)
    p.add_argument("--json", type=Path, help="write the result document here")
    p.add_argument("--method", choices=METHODS, default="slam",
                   help="the proposed method (default) or one of the paper's baselines")
    p.set_defaults(func=cmd_solve)

    p = sub.add_parser("demo", help="simulate and solve the built-in phantom")
    p.add_argument("--out", type=Path, help="case folder (default: a temporary folder)")
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(func=cmd_demo)

    add_bench_parser(sub)
    add_calibrate_parser(sub)
    add_case_parser(sub)
    add_calibration_parser(sub)
    add_measure_parser(sub)
    add_carm_sim_parser(sub)
    add_plan_parser(sub)
    add_status_parser(sub)
    add_replay_parser(sub)
    add_serve_parser(sub)
    add_theatre_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (ValueError, RuntimeError, OSError) as exc:
        print(f"slamtka: error: {_describe_error(exc)}", file=sys.stderr)
        return 2


def _describe_error(exc: Exception) -> str:
    """The message for a refused command: an OSError's own message may not name its file."""
    if isinstance(exc, OSError) and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror or exc}"
    return str(exc)


if __name__ == "__main__":
    sys.exit(main())
