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
Two more kinds of error are the user's: an environment setting the libraries would stop on deep
inside (`environment_problem`: NUMBA_NUM_THREADS=0, a numba threading layer that cannot load,
DETBENCH_MAX_TENSOR_GB=nan), refused before the tool starts, and a path the file system refuses
to write (`unwritable_problem`: read-only, no permission, a file where a folder belongs).
"""
from __future__ import annotations

import argparse
import io
import os
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from detbench.utils.atomic import DiskFullError
from detbench.utils.untrusted import ESCAPE_ERRORS

__all__ = ["EXIT_INTERRUPTED", "EXIT_USER_ERROR", "PARENT_ENV", "UserError", "add_sim_preset_argument",
           "as_user_error", "check_out_dir", "claim_output", "end_with_parent", "environment_problem",
           "is_project_file", "output_folder", "raised_on_purpose", "require", "require_distinct", "run_main",
           "sigterm_as_ctrl_c", "torch_device", "unwritable_problem"]

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


# set by a study's (or the trade sweep's) executor in its jobs' environment: the driver's pid. A job then ends
# with its driver (`end_with_parent`), however the driver ends (a kill -9, an out-of-memory kill)
PARENT_ENV = "DETBENCH_PARENT_PID"


def end_with_parent() -> None:
    """In a job started by an executor (PARENT_ENV set to its driver's pid): have the kernel send this process
    SIGTERM when the driver ends (Linux's parent-death signal; a training then saves its checkpoint and
    exits), and stop at once when the driver has already ended. Nothing elsewhere."""
    want = os.environ.get(PARENT_ENV, "")
    if not want.isdigit():
        return
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            pr_set_pdeathsig = 1
            ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if os.getppid() != int(want):  # the driver ended before the signal was armed
        raise KeyboardInterrupt


NUMBA_LAYERS = ("default", "safe", "forksafe", "threadsafe", "workqueue", "omp", "tbb")


def environment_problem(env=None) -> str | None:
    """What is wrong with a setting of the environment that the libraries would otherwise stop on deep inside
    (numba's thread count and threading layer, DETBENCH_MAX_TENSOR_GB), as one line with the fix; None when
    nothing is."""
    import math

    if env is None:  # with what detbench.runtime set aside at import so that numba could load (not imported here:
        # it is of this layer, and `import detbench` has run it first)
        env = {**os.environ, **getattr(sys.modules.get("detbench.runtime"), "SET_ASIDE", {})}
    threads = env.get("NUMBA_NUM_THREADS")
    if threads is not None and not (threads.strip().isdigit() and int(threads) >= 1):
        return (f"NUMBA_NUM_THREADS={threads}: numba's thread count is a whole number >= 1; set one (e.g. 1) or "
                f"unset it for one per core")
    layer = env.get("NUMBA_THREADING_LAYER")
    if layer is not None and layer not in NUMBA_LAYERS:
        return f"NUMBA_THREADING_LAYER={layer}: one of {', '.join(NUMBA_LAYERS)}; or unset it (detbench uses omp)"
    if layer == "tbb":  # the layer that needs a package of its own (omp, detbench's default, comes with numba)
        import importlib

        try:
            importlib.import_module("numba.np.ufunc.tbbpool")
        except (ImportError, OSError, ValueError):
            return ("NUMBA_THREADING_LAYER=tbb: numba cannot load this layer here (it needs Intel TBB: pip install "
                    "tbb); install it, or unset NUMBA_THREADING_LAYER (detbench then uses omp)")
    cap = env.get("DETBENCH_MAX_TENSOR_GB")
    if cap is not None and cap.strip():
        try:
            gb = float(cap)
        except ValueError:
            gb = math.nan
        if not (math.isfinite(gb) and gb > 0):
            return (f"DETBENCH_MAX_TENSOR_GB={cap}: the largest tensor a model may allocate is a positive number "
                    f"of GiB (e.g. 16, the default when it is unset)")
    return None


def unwritable_problem(e: OSError) -> str | None:
    """One line for a file-system refusal of a path the user chose (a read-only file system, a folder without
    write permission, a file where a folder belongs), naming the path and the fix; None for other errors."""
    import errno

    path = e.filename
    if not path or e.errno not in (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOTDIR, errno.EEXIST):
        return None
    if e.errno == errno.EROFS:
        why = "the file system is read-only"
    elif e.errno in (errno.EACCES, errno.EPERM):
        why = "permission denied"
    else:
        why = "a file stands where a folder belongs"
    return (f"{path}: cannot be written ({why}); choose a folder you can write to (--out, a copy of --data, "
            f"$DETBENCH_CACHE), or make this one writable")


def run_main(main: Callable[[Sequence[str] | None], int], argv: Sequence[str] | None = None) -> int:
    """`main(argv)`, with a `UserError` (or a full disk) printed as one 'error: ...' line and its exit status,
    and Ctrl-C (KeyboardInterrupt) as one 'interrupted' line and 130. Output the terminal cannot encode (a file
    name that is not UTF-8) is printed escaped (`\\xff`)."""
    _escape_unencodable_output()
    problem = environment_problem()
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return EXIT_USER_ERROR
    try:
        with sigterm_as_ctrl_c():
            end_with_parent()
            return main(argv)
    except (UserError, DiskFullError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as e:
        problem = unwritable_problem(e)
        if problem is None:
            raise
        print(f"error: {problem}", file=sys.stderr)
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


def require_distinct(values, flag: str, key=None, what: str = "value") -> None:
    """UserError when `values` (a list option) names one thing twice (compared by `key`, e.g. a height by
    its height key, so 1.8 and 1.80 are one): every figure would count it twice."""
    seen: dict = {}
    for v in values or ():
        k = v if key is None else key(v)
        if k in seen:
            same = f"{v} is given twice" if str(v) == str(seen[k]) else f"{seen[k]} and {v} are one {what}, given twice"
            raise UserError(f"{flag} {' '.join(str(x) for x in values)}: {same}; give each {what} once")
        seen[k] = v


def check_out_dir(path, flag: str = "--out") -> Path:
    """An output folder that can be created or written into: UserError when it is a file, or under one."""
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise UserError(f"{flag} {path}: {p} is a file, not a folder; choose another {flag}")
            break
    return path


def output_folder(path, kind, flag: str = "--out") -> Path:
    """`path` as the output folder of a writer of `kind` (a `FolderKind`, e.g.
    detbench.utils.report_folders.EVAL_FOLDER): `check_out_dir`, then the folder-ownership rule: new, empty or
    proven to be `kind`'s (`check_claimable`), so no file the writer did not write is replaced; UserError
    naming the folder and the fix. Nothing is written (`claim_output` writes)."""
    from detbench.utils.folder_ownership import FolderNotReplaceable, check_claimable

    path = check_out_dir(path, flag)
    try:
        check_claimable(path, kind, out=flag)
    except FolderNotReplaceable as e:
        raise UserError(f"{flag} {e}") from None
    return path


@contextmanager
def claim_output(path, kind, flag: str = "--out") -> Iterator[Path]:
    """Write a report of `kind` into `path` in the block: `output_folder` again, then the folder is made and
    marked as `kind`'s (its owner file). A block that raises before writing anything leaves no folder it
    made."""
    from detbench.utils.folder_ownership import OWNER_FILE, folder_owner, write_owner

    path = output_folder(path, kind, flag)
    created = [p for p in (path, *path.parents) if not p.exists()]
    path.mkdir(parents=True, exist_ok=True)
    if folder_owner(path) is None:
        write_owner(path, kind)
    try:
        yield path
    except BaseException:
        if created and sorted(p.name for p in path.iterdir()) in ([], [OWNER_FILE]):
            (path / OWNER_FILE).unlink(missing_ok=True)
            for p in created:
                try:
                    p.rmdir()
                except OSError:
                    break
        raise


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
