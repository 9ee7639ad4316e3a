"""How commands end: a user's mistake is one line on stderr and exit status 2; a bug is a traceback.

A tool raises `UserError("PATH or KEY: what is wrong; how to fix it")` for anything the user
can fix (a malformed file, a bad config value, a refused or broken checkpoint, a run whose
loss or outputs went NaN, a full disk); its `__main__` guard is `sys.exit(run_main(main))`,
which prints the message and returns exit status 2. `UserError` is a `SystemExit`, so a
tool's `main` called in-process (tests) stops the same way and
`pytest.raises(SystemExit, match=...)` sees the message. Anything else is a bug and keeps
its traceback (exit status 1). Ctrl-C ends with one line and exit status 130 (128 + SIGINT, as a
shell reports it): a tool that saves its work on an interrupt (training, the study, the trade sweep)
has said so by then, and a traceback would bury that. SIGTERM (`kill PID`, and how a stopped study
stops its jobs) is taken as Ctrl-C, so a tool killed so unwinds the same way: a file being
written atomically is dropped rather than left as a stray temporary, and a training saves.
"""
from __future__ import annotations

import argparse
import io
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from detbench.utils.atomic import DiskFullError
from detbench.utils.untrusted import ESCAPE_ERRORS

__all__ = ["EXIT_INTERRUPTED", "EXIT_USER_ERROR", "UserError", "add_sim_preset_argument", "as_user_error",
           "check_out_dir", "is_project_file", "raised_on_purpose", "require", "run_main", "sigterm_as_ctrl_c",
           "torch_device"]

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130


class UserError(SystemExit):
    """A problem the user fixes; `str(e)` is the message, exit status 2."""

    def __init__(self, message: str):
        super().__init__(str(message))
        self.code = EXIT_USER_ERROR


def _escape_unencodable_output() -> None:
    """Print what the terminal cannot encode (a file name that is not UTF-8) escaped, never stop on it."""
    for stream in (sys.stdout, sys.stderr):
        if isinstance(stream, io.TextIOWrapper) and stream.errors in ("strict", "backslashreplace"):
            stream.reconfigure(errors=ESCAPE_ERRORS)


def run_main(main: Callable[[Sequence[str] | None], int], argv: Sequence[str] | None = None) -> int:
    """`main(argv)`, with a `UserError` (or a full disk) printed as one 'error: ...' line and its exit status,
    and Ctrl-C (KeyboardInterrupt) as one 'interrupted' line and 130. Output the terminal cannot encode (a file
    name that is not UTF-8) is printed escaped (`\\xff`)."""
    _escape_unencodable_output()
    try:
        with sigterm_as_ctrl_c():
            return main(argv)
    except (UserError, DiskFullError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


@contextmanager
def sigterm_as_ctrl_c() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt while the block runs, so `kill PID` stops a command as Ctrl-C does
    (a training loop installs its own handler for both and saves first). Only the main thread can set a
    handler; elsewhere (a test's thread) SIGTERM keeps its default."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


_PACKAGE = Path(__file__).resolve().parents[1]  # detbench/
_CHECKOUT = _PACKAGE.parent  # models/, tools/ and tests/ beside it, when run from a checkout
_INSTALLED_DIRS = {"site-packages", "dist-packages"}


def is_project_file(filename: str | Path) -> bool:
    """Whether a source file is this project's: in the detbench package, or elsewhere in its checkout but
    not in an environment installed there (a `.venv/lib/.../site-packages/numpy` inside the checkout is
    numpy's). Installed as a package (no checkout), only the package counts."""
    try:
        path = Path(filename).resolve()
    except (OSError, ValueError):
        return False
    if path.is_relative_to(_PACKAGE):
        return True
    if _INSTALLED_DIRS & set(_CHECKOUT.parts) or not path.is_relative_to(_CHECKOUT):
        return False
    return not _INSTALLED_DIRS & set(path.relative_to(_CHECKOUT).parts)


def raised_on_purpose(e: BaseException) -> bool:
    """Whether `e` comes from a `raise` statement of this project's code (a check that names the problem)
    rather than from inside numpy, numba or torch, or from a line of ours that is not a raise (a call into a
    compiled kernel): the first is the user's to fix, the second a bug whose traceback must stay."""
    frames = traceback.extract_tb(e.__traceback__)
    if not frames:
        return True  # raised and caught without a frame of its own: nothing to tell apart
    last = frames[-1]
    return is_project_file(last.filename) and (last.line or "").lstrip().startswith("raise")


def as_user_error(e: BaseException, prefix: str = "", always: tuple[type[BaseException], ...] = ()) -> UserError:
    """`UserError(prefix + str(e))` for an error of one of the `always` types (the project's own: a config, a
    dataset or a checkpoint error, whose messages name the file and the fix, also when a DataLoader worker
    raised them) or raised on purpose (`raised_on_purpose`); any other error is raised again as it is, so a
    bug (numpy's "negative dimensions not allowed" from a kernel) keeps its traceback and exit status 1
    instead of reading like a mistake in the command. Use as `raise as_user_error(e) from None`."""
    if not isinstance(e, always) and not raised_on_purpose(e):
        raise e
    return UserError(f"{prefix}{e}")


def doc_parser(doc: str, **kwargs) -> argparse.ArgumentParser:
    """A tool's parser from its module docstring: the first paragraph is the description, the rest (examples,
    what it writes) the epilog, laid out as written."""
    head, _, rest = doc.partition("\n\n")
    return argparse.ArgumentParser(description=head, epilog=rest, formatter_class=argparse.RawDescriptionHelpFormatter,
                                   **kwargs)


class _DeprecatedSimPreset(argparse.Action):
    """`--preset NAME` where it names a simulator calibration: stored as --sim-preset, with a note on stderr."""

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"note: {parser.prog}: {option_string} {values} is a deprecated spelling of --sim-preset {values} "
              f"(a simulator calibration from configs/sim.yaml; --preset in train, study, benchmark and tradeoff "
              f"is a training budget); it is accepted for one release, write --sim-preset", file=sys.stderr)
        setattr(namespace, self.dest, values)


def add_sim_preset_argument(parser: argparse.ArgumentParser, default: str = "paper", detail: str = "") -> None:
    """`--sim-preset NAME` (dest `sim_preset`): a simulator calibration, a preset of configs/sim.yaml, not a
    training budget (configs/presets/*.yaml, the --preset of train, study, benchmark and tradeoff). `--preset`
    is kept as its deprecated spelling for one release: accepted, with a note on stderr."""
    parser.add_argument("--sim-preset", dest="sim_preset", default=default, metavar="NAME",
                        help=f"simulator calibration: a preset of configs/sim.yaml (default {default}){detail}; "
                             f"paper (also carla-tm) is calibration v3, the CARLA-like world with CARLA's vehicle "
                             f"blueprints; v2 the same world with per-class size distributions; v1 a world fitted to "
                             f"Table IV with traffic that is not CARLA's; not a training budget")
    parser.add_argument("--preset", dest="sim_preset", action=_DeprecatedSimPreset, metavar="NAME",
                        help="deprecated spelling of --sim-preset, accepted for one release")


def require(ok: bool, message: str) -> None:
    """`UserError(message)` unless `ok`: a one-line check of an argument's value."""
    if not ok:
        raise UserError(message)


def check_out_dir(path, flag: str = "--out") -> Path:
    """An output folder that can be created or written into: UserError when it is a file, or under one."""
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise UserError(f"{flag} {path}: {p} is a file, not a folder; choose another {flag}")
            break
    return path


def torch_device(name: str, flag: str = "--device"):
    """`torch.device(name)`, usable here: UserError for a malformed name or a CUDA device torch cannot see."""
    import torch

    try:
        device = torch.device(name)
    except (RuntimeError, ValueError) as e:
        raise UserError(f"{flag} {name!r}: not a torch device ({e}); e.g. cpu, cuda or cuda:0") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"{flag} {name}: torch sees no CUDA device (CPU-only build or no GPU); use {flag} cpu")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise UserError(f"{flag} {name}: only {torch.cuda.device_count()} CUDA device(s) are visible")
    return device
