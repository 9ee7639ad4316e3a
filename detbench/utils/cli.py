"""How commands end: a user's mistake is one line on stderr and exit status 2; a bug is a traceback.

A tool raises `UserError("PATH or KEY: what is wrong; how to fix it")` for anything the user
can fix (a malformed file, a bad config value, a refused or broken checkpoint, a run whose
loss or outputs went NaN, a full disk); its `__main__` guard is `sys.exit(run_main(main))`,
which prints the message and returns exit status 2. `UserError` is a `SystemExit`, so a
tool's `main` called in-process (tests) stops the same way and
`pytest.raises(SystemExit, match=...)` sees the message. Anything else is a bug and keeps
its traceback (exit status 1).
"""
from __future__ import annotations

import sys
from typing import Callable, Sequence

from detbench.utils.io import DiskFullError

__all__ = ["EXIT_USER_ERROR", "UserError", "run_main"]

EXIT_USER_ERROR = 2


class UserError(SystemExit):
    """A problem the user fixes; `str(e)` is the message, exit status 2."""

    def __init__(self, message: str):
        super().__init__(str(message))
        self.code = EXIT_USER_ERROR


def run_main(main: Callable[[Sequence[str] | None], int], argv: Sequence[str] | None = None) -> int:
    """`main(argv)`, with a `UserError` (or a full disk) printed as one 'error: ...' line and its exit status."""
    try:
        return main(argv)
    except (UserError, DiskFullError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR
