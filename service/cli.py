"""The ``slamtka`` command line.

Every sub-command lives in the module that implements it and is imported only when it runs:
``slamtka status`` (a health check run every few seconds) must not pay for the solver, the
DICOM stack or the simulator. The table below is the one list of commands and their one-line
help; tooling commands (``simulate``, ``demo``, ``theatre``, ``bench``, ``carm-sim``) come from
the ``slamtka.sim`` and ``slamtka.bench`` packages, which the product never imports.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import os
import sys
from typing import NamedTuple

__all__ = ["COMMANDS", "build_parser", "main"]


class Command(NamedTuple):
    """Where a sub-command is implemented: ``module.register(subparsers)`` adds its parser."""

    module: str
    register: str
    help: str


COMMANDS: dict[str, Command] = {
    "serve": Command("slamtka.service.serve", "add_serve_parser",
                     "run the service (DICOM SCP, pipeline, results)"),
    "status": Command("slamtka.service.status", "add_status_parser",
                      "service health: spool, cases, last result, link, metrics"),
    "audit": Command("slamtka.service.audit", "add_audit_parser",
                     "check the audit log"),
    "prune": Command("slamtka.service.retention", "add_prune_parser",
                     "archive idle cases and delete old ones (retention policy)"),
    "plan": Command("slamtka.service.plans", "add_plan_parser", "pre-operative plans: add, list, show"),
    "case": Command("slamtka.service.case_cli", "add_case_parser",
                    "list, show, re-run a case, or start a new pin set"),
    "measure": Command("slamtka.service.measure", "add_measure_parser",
                       "run the service's pipeline offline on DICOM frames"),
    "solve": Command("slamtka.service.solve_case", "add_solve_parser",
                     "measure the resection plane of a case folder"),
    "calibrate": Command("slamtka.service.calibrate", "add_calibrate_parser",
                         "calibrate a C-arm from ball-grid phantom images"),
    "calibration": Command("slamtka.service.calibrations", "add_calibration_parser",
                           "list, show or install the calibrations of the C-arms"),
    "replay": Command("slamtka.service.replay", "add_replay_parser",
                      "read a run's recording headless; check it against a result"),
    "simulate": Command("slamtka.sim.cli", "add_simulate_parser", "write a simulated case folder"),
    "demo": Command("slamtka.sim.cli", "add_demo_parser", "simulate and solve the built-in phantom"),
    "theatre": Command("slamtka.sim.theatre", "add_theatre_parser",
                       "end-to-end demo: the service, a simulated C-arm, the phantom"),
    "carm-sim": Command("slamtka.drivers.carm_sim", "add_carm_sim_parser",
                        "serve the C-arm encoder protocol on a pseudo-terminal"),
    "bench": Command("slamtka.bench.cli", "add_bench_parser",
                     "benchmarks that print figures"),
}


def _chosen_command(argv: list[str]) -> str | None:
    """The sub-command named on the line (the first word that is not an option)."""
    return next((word for word in argv if not word.startswith("-")), None)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser, with ``command``'s full parser loaded and the others listed by name."""
    parser = argparse.ArgumentParser(prog="slamtka", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, entry in COMMANDS.items():
        if name == command:
            getattr(importlib.import_module(entry.module), entry.register)(sub)
        else:
            sub.add_parser(name, help=entry.help)
    return parser


# What slamtka writes is patient data or derived from it: owner read-write, group read,
# nobody else, whatever umask the shell, the container or a test runner handed down.
PRIVATE_UMASK = 0o027


def main(argv: list[str] | None = None) -> int:
    """Run one command; ``argv`` None: this process is the ``slamtka`` program."""
    program = argv is None
    argv = sys.argv[1:] if argv is None else argv
    os.umask(PRIVATE_UMASK)
    command = _chosen_command(argv)
    if program and command == "serve":
        # One thread for OpenBLAS (read when numpy loads, which the command's import does):
        # its workers spin on the second core that the contour extraction and the other
        # requests use, and a run's small products waited for it under load.
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    args = build_parser(command).parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except BrokenPipeError:  # `slamtka status | head`: the reader had enough; not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing left to flush
        return 0
    except (ValueError, RuntimeError, OSError) as exc:
        print(f"slamtka: error: {_describe_error(exc)}", file=sys.stderr)
        return 2
    finally:
        if program:  # the process ends next
            # Python's last garbage collection at exit walks every object the command's
            # imports made (~60,000 after a solve: ~0.03 s CPU) only to free memory the OS
            # takes back anyway. Frozen, they are skipped; atexit handlers and the modules'
            # teardown still run, and every file a command writes is closed by the time it
            # returns.
            gc.freeze()


def _describe_error(exc: Exception) -> str:
    """The message for a refused command: an OSError's own message may not name its file."""
    if isinstance(exc, OSError) and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror or exc}"
    return str(exc)


if __name__ == "__main__":
    sys.exit(main())
