"""Command line: ``aqfg simulate | import | info | fit | diagnose | fleet | live | demo | bench``.

Each command's work lives in ``aqfg.commands.<name>.run(args)``; this module parses, sets
up logging and maps failures to exit codes: 0 done, 1 internal error, 2 usage error (the
command line), 3 data error (the input), 130 interrupted. No command ends in a traceback
(``-v`` prints it for internal errors).
"""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings

from aqfg.commands.common import (
    EXIT_DATA,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_USAGE,
    UsageError,
)


def _effect_setting(text: str) -> tuple[str, str]:
    name, _, val = text.partition("=")
    return name.strip(), val.strip()


def _max_knots(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected >= 0 (0 = no limit), got {v}")
    return v


def _directory(text: str):
    """An output directory's path: not empty (which would write into the working
    directory), no NUL character (else an ``Invalid``: a usage error)."""
    from aqfg.commands.options import Invalid
    if not text.strip():
        return Invalid(text, "expected a directory path, got an empty string (write into "
                             "the current directory with '.')")
    if "\0" in text:
        return Invalid(text, "a path cannot hold a NUL character")
    return text


def build_parser() -> argparse.ArgumentParser:
    from aqfg import __version__
    from aqfg.commands.options import number
    count = number(1, 1024, integer=True)
    ap = argparse.ArgumentParser(
        prog="aqfg",
        description="Estimate the motion-model parameters of small AUVs/ASVs from their logs "
                    "(factor-graph smoothing, and the update-error EKF method as baseline), "
                    "and diagnose which physics the model is missing.",
        epilog="exit codes: 0 done, 1 internal error, 2 usage error, 3 data error, "
               "130 interrupted")
    ap.add_argument("--version", action="version", version=f"aqfg {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    g = common.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_const", const=-1, dest="verbosity",
                   default=0, help="only warnings and errors on stderr (no progress)")
    g.add_argument("-v", "--verbose", action="store_const", const=1, dest="verbosity",
                   help="details on stderr, and the traceback of an internal error")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    _add = sub.add_parser

    def add_parser(*a, **kw):
        return _add(*a, parents=[common], **kw)
    sub.add_parser = add_parser                 # type: ignore[method-assign]

    _simulate_parser(sub)
    _import_parser(sub)
    _info_parser(sub)
    for name, hlp in (("fit", "estimate parameters and the trajectory"),
                      ("diagnose", "find which physical effect the model is missing")):
        _job_parser(sub, name, hlp, count)
    _fleet_parser(sub, count)
    _live_parser(sub)
    _demo_parser(sub)
    _bench_parser(sub, count)
    return ap


def _simulate_parser(sub) -> None:
    """``aqfg simulate``."""
    from aqfg.commands.options import MAX_SECONDS, number, seconds
    s = sub.add_parser("simulate", help="simulate a mission (with optional hidden effects)",
                       description="Simulate an ASV or AUV mission in aqfg-mission/1 format.")
    s.add_argument("out_dir", metavar="OUT_DIR", type=_directory)
    s.add_argument("--vehicle", choices=["asv", "auv"], default="asv")
    s.add_argument("--seed", type=number(0, 2**32 - 1, integer=True), default=0)
    s.add_argument("--duration", type=seconds(), default=600.0,
                   help=f"seconds (default 600, at most {MAX_SECONDS:g})")
    s.add_argument("--effect", action="append", default=[], metavar="NAME[=VALUE]",
                   type=_effect_setting,
                   help="hidden effect, e.g. thrust_asymmetry=0.8 or lever_arm.x=0.4; repeatable")
    s.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   type=_effect_setting, help="true base parameter, e.g. theta_e=0.5; repeatable")
    s.add_argument("--gnss-period", type=seconds(zero=True), default=1.0,
                   help="seconds between GNSS fixes; 0 = no GNSS (default 1)")
    s.add_argument("--usbl", action="store_true", help="record USBL range/bearing every 4.5 s")
    s.add_argument("--force", action="store_true", help="overwrite OUT_DIR if it holds a mission")


def _import_parser(sub) -> None:
    """``aqfg import``."""
    s = sub.add_parser("import", help="convert a vehicle log (ROS bag, MAVLink, ULog, NMEA, "
                                      "CSV) into a mission",
                       description="Read a ROS 2/1 bag, MAVLink tlog or DataFlash .bin, PX4 "
                                   "ULog, NMEA log or CSV export into aqfg-mission/1 (NMEA: "
                                   "adds GNSS fixes to an existing mission). See "
                                   "docs/mission-format.md.")
    s.set_defaults(module="import_")
    s.add_argument("format", metavar="FORMAT",
                   choices=["ros2", "ros1", "mavlink", "ulog", "nmea", "csv"],
                   help="ros2, ros1, mavlink, ulog, nmea or csv")
    s.add_argument("source", metavar="SOURCE", nargs="+",
                   help="the log file (or ROS 2 bag directory); csv: one or more files, one "
                        "mission each")
    s.add_argument("--out", required=True, metavar="MISSION", type=_directory,
                   help="mission directory to write (csv with several files: the directory "
                        "that receives one mission per file, named after the file)")
    s.add_argument("--map", metavar="MAP.toml",
                   help="vehicle, thrusters, origin and topics (csv: columns) the log does not say")
    s.add_argument("--force", action="store_true", help="overwrite an existing mission "
                                                        "(nmea: replace its GNSS fixes)")


def _info_parser(sub) -> None:
    """``aqfg info``."""
    s = sub.add_parser("info", help="summarise a mission: streams, durations, rates, gaps",
                       description="Load a mission and print what it holds.")
    s.add_argument("mission", metavar="MISSION")


def _job_parser(sub, name: str, hlp: str, count) -> None:
    """``fit`` or ``diagnose``: the options they share, then their own."""
    from aqfg.commands.options import seconds
    from aqfg.limits import DEFAULT_MAX_KNOTS
    s = sub.add_parser(name, help=hlp, description=hlp[0].upper() + hlp[1:] + ".")
    s.add_argument("missions", nargs="+", metavar="MISSION")
    s.add_argument("--out", required=True, metavar="DIR", type=_directory,
                   help="output directory")
    s.add_argument("--effect", action="append", default=[], metavar="NAME",
                   help="add a model effect (repeatable)")
    s.add_argument("--gnss-every", type=seconds(zero=True), default=0.0, metavar="S",
                   help="use one GNSS fix every S seconds (default: all)" if name == "fit"
                   else "held-out split: fit on one GNSS fix every S seconds (and every "
                        "other USBL fix), test dead reckoning on the rest (default 8)")
    s.add_argument("--force", action="store_true",
                   help="replace the previous outputs in DIR (the whole set)")
    s.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    s.add_argument("--max-knots", type=_max_knots, default=DEFAULT_MAX_KNOTS, metavar="N",
                   help="refuse missions needing a graph of more than N state knots "
                        f"(one per second of mission; default {DEFAULT_MAX_KNOTS:,}, "
                        "0 = no limit)")
    if name == "fit":
        s.add_argument("--tum", action="store_true",
                       help="also write trajectory.tum (TUM format, for evo)")
    if name == "diagnose":
        _diagnose_options(s, count)
    if name == "fit":
        _fit_options(s)


def _diagnose_options(s, count) -> None:
    """``aqfg diagnose``'s own options."""
    s.add_argument("--auto", action="store_true",
                   help="diagnose, add the missing effect, refit, and again until "
                        "nothing more is confirmed; writes model.json")
    s.add_argument("--max-steps", type=count, default=6, metavar="N",
                   help="--auto: add at most N effects (default 6)")
    s.add_argument("--stop-when-consistent", action="store_true",
                   help="--auto: also stop once the held-out fixes are consistent "
                        "with the model")
    from aqfg.commands.options import number
    s.add_argument("--min-gain", type=number(0.0, 1.0), default=None, metavar="F",
                   help="name an effect missing only when it lowers the held-out "
                        "dead-reckoning error beyond the fixes' noise by at least this "
                        "fraction (default 0.1)")
    s.add_argument("--jobs", type=count, default=None, metavar="N",
                   help="worker processes for the candidates' refits "
                        "(default: the CPUs available, at most 4)")


def _fit_options(s) -> None:
    """``aqfg fit``'s own options (after ``--tum``)."""
    from aqfg.commands.options import seconds
    s.add_argument("--model", metavar="MODEL_JSON",
                   help="start from a learned model (model.json of aqfg diagnose): "
                        "its effects, and its vehicle parameters as initial values")
    s.add_argument("--method", choices=["fg", "update-error"], default="fg",
                   help="fg: factor-graph smoothing (default); update-error: the "
                        "paper's EKF method, the baseline (same outputs)")
    s.add_argument("--mode", choices=["batch", "online"], default="batch",
                   help="batch: all fixes at once (default); online: fix by fix, "
                        "causally (fg: fixed-lag smoother; update-error: windowed EKF)")
    s.add_argument("--window", type=seconds(), default=None,
                   help="online window, seconds (fg default 24; update-error: last 3 fixes)")
    s.add_argument("--estimate", default=None, metavar="NAMES",
                   help="comma-separated parameters to estimate (default: batch, the "
                        "six base parameters and those of the effects; online fg, "
                        "theta_e,s_x,s_y and the effects' per-mission ones, plus "
                        "k,k_x,k_yz unless --params-from, --model or --init gives one "
                        "of them; online update-error, theta_e,s_x,s_y)")
    s.add_argument("--init", action="append", default=[], metavar="NAME=VALUE",
                   type=_effect_setting, help="initial/fixed value of a parameter")
    s.add_argument("--params-from", metavar="JSON",
                   help="take fixed values from a previous parameters.json (and "
                        "the effects of its model)")
    s.add_argument("--no-auto-effect", action="store_true",
                   help="fg batch: fit the model as given, without adding the "
                        "effect a structural test finds missing")


def _fleet_parser(sub, count) -> None:
    """``aqfg fleet``."""
    from aqfg.commands.options import seconds
    s = sub.add_parser("fleet", help="calibrate every vehicle of a fleet from all its missions",
                       description="Each vehicle's joint fit over its missions (a TOML "
                                   "manifest), solved in parallel on Dask.")
    s.add_argument("manifest", metavar="MANIFEST")
    s.add_argument("--out", required=True, metavar="DIR", type=_directory,
                   help="output directory")
    s.add_argument("--workers", type=count, default=2,
                   help="local worker processes (default 2; ignored with --scheduler)")
    s.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="a running Dask scheduler, e.g. tcp://host:8786")
    s.add_argument("--diagnose", action="store_true", help="also diagnose each mission")
    s.add_argument("--effect", action="append", default=[], metavar="NAME",
                   help="add a model effect (repeatable)")
    s.add_argument("--gnss-every", type=seconds(zero=True), default=0.0, metavar="S",
                   help="use one GNSS fix every S seconds (default: all)")
    s.add_argument("--no-auto-effect", action="store_true",
                   help="fit the model as given, without adding the effect the vehicles' "
                        "structural tests find missing")
    s.add_argument("--force", action="store_true", help="overwrite existing outputs")


def _live_parser(sub) -> None:
    """``aqfg live``."""
    from aqfg.commands.options import number, seconds
    s = sub.add_parser("live", help="run the online smoother on a MAVLink stream (or a "
                                     "tlog replayed as one)",
                       description="Run the fixed-lag smoother of 'aqfg fit --mode online' on "
                                   "a MAVLink connection, or on a .tlog or DataFlash .bin "
                                   "replayed at --speed; "
                                   "writes live.jsonl and causal.csv as it goes, the fit's "
                                   "outputs at the end (or on Ctrl-C). See "
                                   "docs/on-the-vehicle.md.")
    s.add_argument("source", metavar="SOURCE",
                   help="a .tlog or DataFlash .bin, or a MAVLink connection: udpin:0.0.0.0:14550, "
                        "udp:HOST:PORT, tcp:HOST:PORT, /dev/ttyUSB0,57600")
    s.add_argument("--map", required=True, metavar="MAP.toml",
                   help="vehicle, thrusters, origin and messages (as for aqfg import mavlink)")
    s.add_argument("--out", required=True, metavar="DIR", type=_directory,
                   help="output directory")
    s.add_argument("--params-from", metavar="JSON",
                   help="the vehicle's constants from a previous parameters.json (and the "
                        "effects of its model, and its GNSS noise)")
    s.add_argument("--model", metavar="MODEL_JSON",
                   help="start from a learned model (model.json of aqfg diagnose)")
    s.add_argument("--window", type=seconds(), default=None,
                   help="the smoother's window, seconds (default 24)")
    s.add_argument("--speed", type=number(0.0, 1e6), default=None, metavar="X",
                   help="a log's replay: X times real time (default 1; 0 = as fast as "
                        "possible)")
    s.add_argument("--send-to", metavar="ENDPOINT", default=None,
                   help="send the corrected position (GPS_INPUT) and the parameters "
                        "(NAMED_VALUE_FLOAT) to this MAVLink endpoint, e.g. "
                        "udpout:127.0.0.1:14551 (default: send nothing)")
    s.add_argument("--force", action="store_true",
                   help="replace the previous outputs in DIR (the whole set)")


def _demo_parser(sub) -> None:
    """``aqfg demo``."""
    s = sub.add_parser("demo", help="the main job on a built-in simulated mission",
                       description="Simulate a mission, fit it with the factor graph and the "
                                   "update-error baseline, diagnose it, and write a report.")
    s.add_argument("--out", default="aqfg-demo", metavar="DIR", type=_directory)
    s.add_argument("--force", action="store_true", help="overwrite DIR")


def _bench_parser(sub, count) -> None:
    """``aqfg bench``."""
    s = sub.add_parser("bench", help="quick benchmarks (medians of repeated runs)",
                       description="Measure kernel, fixed-lag, update-error and batch timings.")
    s.add_argument("--repeat", type=count, default=5)
    s.add_argument("--quick", action="store_true",
                   help="a 20-minute online stream instead of 2 hours, and --repeat runs of "
                        "each command instead of at least 5 (the other figures alike)")
    s.add_argument("--out", default=None, metavar="DIR", type=_directory,
                   help="also write bench.md here")
    s.add_argument("--force", action="store_true", help="replace an existing DIR/bench.md")


def _by_interrupt(e: BaseException) -> bool:
    """An exception raised because of Ctrl-C (a native module's import fails with
    ImportError when interrupted during its initialisation)."""
    seen = set()
    cur: BaseException | None = e
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return True
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return False


def check_options(ap: argparse.ArgumentParser, argv: list[str]) -> None:
    """A command's option that it does not have: the command's usage and the closest option
    it has (argparse itself shows the top-level usage and suggests nothing; its own
    ``suggest_on_error`` needs Python >= 3.14). Exits 2 as argparse does."""
    import difflib
    commands: dict[str, argparse.ArgumentParser] = next(
        (a.choices for a in ap._actions if isinstance(a, argparse._SubParsersAction)), {})
    i = next((i for i, tok in enumerate(argv) if tok in commands), None)
    if i is None:
        return
    p = commands[argv[i]]
    opts = [o for a in p._actions for o in a.option_strings]
    for tok in argv[i + 1:]:
        if tok == "--":
            break
        name = tok.split("=", 1)[0]
        if len(name) < 2 or name[0] != "-" or name in opts or p._negative_number_matcher.match(name):
            continue
        if name.startswith("--") and any(o.startswith(name) for o in opts):
            continue                      # an abbreviation: argparse's to take or refuse
        close = difflib.get_close_matches(name, [o for o in opts if o.startswith("--")], n=1,
                                          cutoff=0.6)
        p.error(f"unrecognized option {name}" + (f"; did you mean {close[0]}?" if close else
                f" (see aqfg {argv[i]} --help)"))


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns the exit code."""
    try:
        return _main(argv)
    except KeyboardInterrupt:            # while the parser and the modules load
        print("\naqfg: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _main(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = build_parser()
    check_options(ap, argv)
    args = ap.parse_args(argv)
    from aqfg import outputs
    from aqfg.commands import common
    from aqfg.data.io import MissionFormatError
    outputs.COMMAND_LINE = ["aqfg", *argv]
    name = args.command

    def fail(code: int, msg: object, kind: str = "error") -> int:
        print(f"aqfg {name}: {kind}: {common.printable(msg)}", file=sys.stderr)
        return code

    with warnings.catch_warnings():
        common.setup(name, args.verbosity)
        try:
            from aqfg.commands.options import check_parsed
            check_parsed(args)
            mod = importlib.import_module(f"aqfg.commands.{getattr(args, 'module', name)}")
            code = int(mod.run(args) or 0)
            common.summary(getattr(args, "missions", None) or ())
            return code
        except KeyboardInterrupt:
            print(f"\naqfg {name}: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        except BrokenPipeError:          # output piped into e.g. `head`: not an error
            sys.stderr.close()
            return 0
        except (UsageError, FileExistsError, KeyError) as e:
            return fail(EXIT_USAGE, e.args[0] if isinstance(e, KeyError) and e.args else e)
        except (MissionFormatError, FileNotFoundError, NotADirectoryError, ValueError) as e:
            return fail(EXIT_DATA, e)
        except OSError as e:
            return fail(EXIT_INTERNAL, f"{e.strerror or e}"
                        + (f": {e.filename}" if e.filename else ""))
        except Exception as e:  # noqa: BLE001 - a fault in aqfg: one line (-v: traceback)
            if _by_interrupt(e):
                print(f"\naqfg {name}: interrupted", file=sys.stderr)
                return EXIT_INTERRUPTED
            if common.verbose():
                import traceback
                traceback.print_exc()
            return fail(EXIT_INTERNAL, f"{type(e).__name__}: {e} (an internal error; "
                        "run with -v for the traceback)", "internal error")


if __name__ == "__main__":
    sys.exit(main())
