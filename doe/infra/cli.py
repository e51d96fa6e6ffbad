"""The ``doefab`` command line: one subcommand per stage, dispatched to its package.

Each command module exposes ``register(subparsers)``; heavy imports (torch,
build123d, klayout) happen inside the commands, so ``doefab --help`` is fast and
``doe`` never imports torch.
"""

import argparse
import importlib
import os
import re
import signal
import sys

from doe.infra import interrupts
from doe.infra.errors import InputError

COMMAND_MODULES = (
    "doe.commands.design",  # presets, config
    "doe.commands.retrieve",  # retrieve
    "doe.commands.camera",  # camera
    "psf_learn.commands.learn",  # learn, evaluate, sr
    "psf_learn.commands.camera_psnr",  # camera-psnr
    "fab.commands.fab",  # fab
    "fab.commands.mesh",  # mesh
    "fab.commands.verify",  # verify, mtf
    "fab.commands.simulate_capture",  # simulate-capture
    "psf_learn.commands.depth",  # depth, transient
    "fab.commands.run",  # run
)


def build_parser():
    """Return the argparse parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="doefab",
        description="Design and fabricate diffractive phase plates for low-fill-factor sensors.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


INTERNAL_ERROR = 3  # exit code of a bug, apart from the contract's 0, 1 and 2


def main(argv=None):
    """Run the command line; return the exit code (0 ok, 1 check failed, 2 bad input, 3 bug)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    # A command that runs other commands (run: one per stage) is handed the dispatcher
    # rather than importing it back, which would make an import circle.
    args.invoke = main
    # Ctrl-C and SIGTERM unwind, so that staging folders are removed, and are remembered
    # when a library swallows their exception.
    with interrupts.handled():
        return _dispatch(args)


def _dispatch(args):
    try:
        try:
            if getattr(args, "out", None) is not None and not args.out.strip():
                # An unset shell variable ($OUT) would otherwise mean the current folder.
                raise InputError("--out", "is empty")
            code = int(args.func(args) or 0)
            interrupts.check()  # asked to stop, though nlopt took it for a stop and went on
            sys.stdout.flush()  # a closed pipe shows here, in the handlers below, not at exit
            return code
        except Exception:
            interrupts.check()  # the signal, not what it broke ("Invalid bounding box")
            raise
    except InputError as e:  # one line, even when it quotes a library's page of text
        print(f"doefab {args.command}: error: {_one_line(str(e))}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of stdout stopped (| head): end quietly, as SIGPIPE would
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + 13
    except OSError as e:  # the file system refused: an unwritable --out, a full disk
        where = e.filename if e.filename is not None else "file system"
        print(f"doefab {args.command}: error: {where}: {e.strerror or e}", file=sys.stderr)
        return 2
    except interrupts.Terminated:
        print(f"doefab {args.command}: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print(f"doefab {args.command}: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print(
            f"doefab {args.command}: error: out of memory (an input too large for this machine?)",
            file=sys.stderr,
        )
        return 2
    except Exception:  # a bug: Python's exit 1 would read as "check failed" (verify: "fails")
        import traceback

        traceback.print_exc()
        print(
            f"doefab {args.command}: internal error (a bug in doefab, not a verdict on the "
            f"input; please report the traceback above): exit {INTERNAL_ERROR}",
            file=sys.stderr,
        )
        return INTERNAL_ERROR


def _one_line(text):
    """Return text with its line breaks (and the indentation after them) as single spaces."""
    return re.sub(r"[ \t]*[\r\n]+\s*", " ", text.strip())


if __name__ == "__main__":
    sys.exit(main())
