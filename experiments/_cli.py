"""Shared entry-point wrapper: user errors become one line on stderr and a non-zero exit.

Every ``experiments.*`` module ends with ``_cli.run(main)``. Exit codes a script can trust:

- 0: done;
- 2: a user error (bad argument, missing or unreadable file, bad data): ``error: <message>``
  on one line, no traceback (argparse uses 2 for its own errors too);
- 3: reserved for "ran, but the answer is negative" where a command defines it
  (``experiments.hang``: no candidate hangs);
- 130: interrupted (Ctrl+C);
- 1: anything else, an internal error, with its traceback (a bug to report).

Set ``OMNIHANG_DEBUG=1`` to get the traceback of user errors too.
"""

from __future__ import annotations

import os
import sys
import traceback
import zipfile
from collections.abc import Callable

EXIT_OK, EXIT_INTERNAL, EXIT_USER, EXIT_NEGATIVE, EXIT_INTERRUPTED = 0, 1, 2, 3, 130

# Exceptions that mean "the input is wrong", not "the code is wrong". ValueError covers
# sim.meshio.MeshError and omnihang_jax.hang.HangInputError (both subclass it).
USER_ERRORS: tuple[type[BaseException], ...] = (
    ValueError,
    FileNotFoundError,
    NotADirectoryError,
    IsADirectoryError,
    PermissionError,
    FileExistsError,
    zipfile.BadZipFile,
    EOFError,
)


def _file_in_traceback(exc: BaseException) -> str | None:
    """The file a loader was reading when ``exc`` was raised (a ``file``/``path``/``fname``
    string argument of the innermost frame that has one), for errors that do not name it
    (numpy's BadZipFile, a truncated pickle)."""
    tb = exc.__traceback__
    found = None
    while tb is not None:
        local = tb.tb_frame.f_locals
        for key in ("file", "path", "fname", "filename"):
            value = local.get(key)
            if isinstance(value, str | os.PathLike) and os.path.exists(os.fspath(value)):
                found = os.fspath(value)
        tb = tb.tb_next
    return found


def user_message(exc: BaseException) -> str:
    """One line: the error's message, with the file named when the message lacks it."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    name = getattr(exc, "filename", None)
    if name and os.fspath(name) not in text:
        text = f"{os.fspath(name)}: {text}"
    elif not isinstance(exc, ValueError) or isinstance(exc, zipfile.BadZipFile):
        where = _file_in_traceback(exc)
        if where and where not in text:
            text = f"{where}: {type(exc).__name__}: {text}"
    return text


def run(main: Callable, argv: list[str] | None = None) -> None:
    """Call ``main(argv)`` and exit with a code from the table above. ``main`` may return an
    int (its exit code) or anything else (0)."""
    try:
        code = main(argv)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)
    except SystemExit:
        raise
    except USER_ERRORS as exc:
        if os.environ.get("OMNIHANG_DEBUG"):
            traceback.print_exc()
        print(f"error: {user_message(exc)}", file=sys.stderr)
        sys.exit(EXIT_USER)
    sys.exit(code if isinstance(code, int) and not isinstance(code, bool) else EXIT_OK)
