"""Command line: ``aqfg simulate | info | fit | diagnose | demo | bench``.

Each command's work lives in ``aqfg.commands.<name>.run(args)``; this module only parses.
"""
from __future__ import annotations

import argparse
import importlib
import sys


def _effect_setting(text: str) -> tuple[str, str]:
    name, _, val = text.partition("=")
    return name.strip(), val.strip()


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="aqfg",
        description="Estimate the motion-model parameters of small AUVs/ASVs from their logs "
                    "(factor-graph smoothing, and the update-error EKF method as baseline), "
                    "and diagnose which physics the model is missing.")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    s = sub.add_parser("simulate", help="simulate a mission (with optional hidden effects)",
                       description="Simulate an ASV or AUV mission in aqfg-mission/1 format.")
    s.add_argument("out_dir", metavar="OUT_DIR")
    s.add_argument("--vehicle", choices=["asv", "auv"], default="asv")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--duration", type=float, default=600.0, help="seconds (default 600)")
    s.add_argument("--effect", action="append", default=[], metavar="NAME[=VALUE]",
                   type=_effect_setting,
                   help="hidden effect, e.g. thrust_asymmetry=0.8 or lever_arm.x=0.4; repeatable")
    s.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   type=_effect_setting, help="true base parameter, e.g. theta_e=0.5; repeatable")
    s.add_argument("--gnss-period", type=float, default=1.0,
                   help="seconds between GNSS fixes; 0 = no GNSS (default 1)")
    s.add_argument("--usbl", action="store_true", help="record USBL range/bearing every 4.5 s")
    s.add_argument("--force", action="store_true", help="overwrite OUT_DIR if it holds a mission")

    s = sub.add_parser("info", help="summarise a mission: streams, durations, rates, gaps",
                       description="Load a mission and print what it holds.")
    s.add_argument("mission", metavar="MISSION")

    for name, hlp in (("fit", "estimate parameters and the trajectory"),
                      ("diagnose", "find which physical effect the model is missing")):
        s = sub.add_parser(name, help=hlp, description=hlp[0].upper() + hlp[1:] + ".")
        s.add_argument("missions", nargs="+", metavar="MISSION")
        s.add_argument("--out", required=True, metavar="DIR", help="output directory")
        s.add_argument("--effect", action="append", default=[], metavar="NAME",
                       help="add a model effect (repeatable)")
        s.add_argument("--gnss-every", type=float, default=0.0, metavar="S",
                       help="use one GNSS fix every S seconds (default: all)" if name == "fit"
                       else "held-out split: fit on one GNSS fix every S seconds (and every "
                            "other USBL fix), test dead reckoning on the rest (default 8)")
        s.add_argument("--force", action="store_true", help="overwrite existing outputs")
        s.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
        if name == "fit":
            s.add_argument("--method", choices=["fg", "update-error"], default="fg")
            s.add_argument("--mode", choices=["batch", "online"], default="batch")
            s.add_argument("--window", type=float, default=None,
                           help="online window, seconds (fg default 24; update-error: last 3 fixes)")
            s.add_argument("--estimate", default=None,
                           help="comma-separated parameters to estimate "
                                "(default: all six in batch, theta_e,s_x,s_y online)")
            s.add_argument("--init", action="append", default=[], metavar="NAME=VALUE",
                           type=_effect_setting, help="initial/fixed value of a parameter")
            s.add_argument("--params-from", metavar="JSON",
                           help="take fixed values from a previous parameters.json")

    s = sub.add_parser("demo", help="the main job on a built-in simulated mission",
                       description="Simulate a mission, fit it with the factor graph and the "
                                   "update-error baseline, diagnose it, and write a report.")
    s.add_argument("--out", default="aqfg-demo", metavar="DIR")
    s.add_argument("--force", action="store_true", help="overwrite DIR")

    s = sub.add_parser("bench", help="quick benchmarks (medians of repeated runs)",
                       description="Measure kernel, fixed-lag, update-error and batch timings.")
    s.add_argument("--repeat", type=int, default=5)
    s.add_argument("--out", default=None, metavar="DIR", help="also write bench.md here")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    mod = importlib.import_module(f"aqfg.commands.{args.command}")
    try:
        return int(mod.run(args) or 0)
    except BrokenPipeError:          # output piped into e.g. `head`: not an error
        sys.stderr.close()
        return 0
    except (FileNotFoundError, FileExistsError, ValueError, KeyError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"aqfg {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
