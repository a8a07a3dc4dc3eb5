"""``slamtka simulate`` and ``slamtka demo``: simulated case folders, and the built-in case
simulated then measured."""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

from slamtka.service.solve_case import cmd_solve
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.calibration_set import write_calibration_set
from slamtka.sim.case_images import write_case_images
from slamtka.sim.operating_room import NUISANCES, OperatingRoom, view_angles
from slamtka.sim.simulate import SimulationConfig, simulate_case
from slamtka.solver.case import write_case
from slamtka.solver.plan import Plan

__all__ = ["add_simulate_parser", "add_demo_parser", "cmd_simulate", "cmd_demo"]


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
        plan = phantom_plan(args.side)
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
    pixels = getattr(args, "detector_pixels", None)
    if pixels is not None and not 256 <= pixels <= 4096:
        raise ValueError(f"--detector-pixels must be 256 to 4096, got {pixels}")
    config = SimulationConfig(view_angles_deg=views, noise_px=args.noise_px, seed=args.seed,
                              init_rot_sd_rad=args.init_rot_sd, init_trans_sd_mm=args.init_trans_sd,
                              detector_pixels=pixels)
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
    flags: dict[str, Any] = {name: True for name in NUISANCES if getattr(args, name, False)}
    return replace(base, **flags)


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
    folder = Path(__file__).resolve().parents[3] / "shared" / "data" / "knee-nuisance"
    return folder if folder.is_dir() else None


def add_simulate_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="write a simulated case folder")
    p.add_argument("--out", type=Path, required=True)
    _add_model_options(p)
    p.add_argument("--views", type=_floats, default=(-30.0, 30.0),
                   help="view angles about the leg axis, degrees (0 = AP)")
    p.add_argument("--noise-px", type=float, default=2.0)
    p.add_argument("--init-rot-sd", type=float, default=0.1, help="initial rotation error SD, rad")
    p.add_argument("--init-trans-sd", type=float, default=20.0, help="initial translation error SD, mm")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--detector-pixels", type=int, metavar="N",
                   help="the detector's pixels a side (default 1024; a flat panel's 1536 or 2048 "
                        "over the same field)")
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
                       help=f"add the {name.replace('_', ' ')} nuisance (solver/sim/operating_room.py)")
    p.add_argument("--nuisance-meshes", type=Path, default=_shared_meshes(),
                   help="folder with femur-generic-right.stl and patella-right.stl (metres)")
    p.add_argument("--patient-id", help="Patient ID of the plan and the frames (default: the plan's)")
    p.add_argument("--patient-name", help="Patient's Name in the frames (default: the Patient ID)")
    p.set_defaults(func=cmd_simulate)


def add_demo_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="simulate and solve the built-in phantom")
    p.add_argument("--out", type=Path, help="case folder (default: a temporary folder)")
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(func=cmd_demo)
