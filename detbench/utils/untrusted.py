"""Reading what someone else wrote: a file's content never reaches a message whole, and never leads out of
the folder the user named.

- `excerpt(value)`: the short, escaped rendering of untrusted content (a line, a field, a key, a frame id)
  that every error quoting a file's content uses: at most `EXCERPT_CHARS` characters of a string, with
  control characters, terminal escapes and undecodable bytes escaped, and the length said when cut;
  containers shown by their first few items, anything else by its type.
- `clip(text)`: an exception's own message (which may quote content) cut and escaped the same way.
- `outside_folder(path, root)`: where a path really leads when that is outside `root` (a link out of the
  folder), else None; readers refuse such files rather than echo or use another folder's content.
- `structure_problem(obj)`: what is wrong with a loaded JSON / YAML / pickle structure that would blow up
  whatever walks it later: nested deeper than `MAX_DEPTH`, holding itself, or expanding (through YAML
  aliases or shared pickle references) to more values than a limit.
- `ESCAPE_ERRORS`: the codec error handler the tools print and write text with, so a file name that is not
  UTF-8 (undecodable bytes kept as surrogates) shows its bytes as `\\xff` instead of stopping the command.
"""
from __future__ import annotations

import codecs
import os
from pathlib import Path
from typing import Any

EXCERPT_CHARS = 40  # characters of untrusted text a message quotes
CLIP_CHARS = 300  # characters of an exception's message quoted in ours
MAX_DEPTH = 64  # nesting levels of a loaded JSON / YAML / pickle structure
EXCERPT_ITEMS = 4  # items of a container shown

ESCAPE_ERRORS = "detbench-escape"


def _escape_unencodable(err: UnicodeError) -> tuple[str, int]:
    """Codec error handler: a surrogate holding an undecodable byte as `\\xNN`, anything else backslash-escaped."""
    if not isinstance(err, UnicodeEncodeError):
        raise err
    out = []
    for c in err.object[err.start:err.end]:
        o = ord(c)
        out.append(f"\\x{o - 0xDC00:02x}" if 0xDC80 <= o <= 0xDCFF else c.encode("ascii", "backslashreplace")
                   .decode("ascii"))
    return "".join(out), err.end


codecs.register_error(ESCAPE_ERRORS, _escape_unencodable)


def _quoted(text: str | bytes, limit: int) -> str:
    cut = text[:limit]
    shown = repr(bytes(cut)) if isinstance(text, bytes) else repr(str(cut))
    if len(text) <= limit:
        return shown
    return f"{shown}... ({len(text)} {'bytes' if isinstance(text, bytes) else 'characters'})"


def excerpt(value: Any, limit: int = EXCERPT_CHARS, _depth: int = 1) -> str:
    """A short, escaped rendering of untrusted `value` for a message (see the module doc); never long, never
    slow, whatever `value` holds."""
    if isinstance(value, (str, bytes)):
        return _quoted(value, limit)
    if value is None or isinstance(value, (bool, float)):
        return repr(value)
    if isinstance(value, int):
        return repr(value) if value.bit_length() <= 64 else f"<an integer of {value.bit_length()} bits>"
    if hasattr(value, "dtype") and hasattr(value, "shape"):  # numpy arrays and scalars
        if getattr(value, "ndim", 0) == 0 and _depth >= 0 and value.dtype.kind in "biufcUSO":
            return excerpt(value.item(), limit, _depth - 1)
        return f"<an array of shape {tuple(value.shape)}, dtype {value.dtype.str}>"
    if isinstance(value, (list, tuple, dict, set, frozenset)):
        kind = "a mapping" if isinstance(value, dict) else f"a {type(value).__name__}"
        if _depth <= 0:
            return f"<{kind} of {len(value)} item(s)>"
        items = []
        for i, item in enumerate(value.items() if isinstance(value, dict) else value):
            if i == EXCERPT_ITEMS:
                items.append(f"... ({len(value)} items)")
                break
            items.append(f"{excerpt(item[0], limit, _depth - 1)}: {excerpt(item[1], limit, _depth - 1)}"
                         if isinstance(value, dict) else excerpt(item, limit, _depth - 1))
        left, right = {dict: "{}", list: "[]", tuple: "()"}.get(type(value), "{}")
        return left + ", ".join(items) + right
    return f"<a {type(value).__name__}>"


def clip(text: str, limit: int = CLIP_CHARS) -> str:
    """`text` (an exception's message, which may quote file content) with control characters escaped, cut to
    `limit` characters."""
    text = str(text)
    shown = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text[:limit])
    return shown + (f"... ({len(text)} characters)" if len(text) > limit else "")


def outside_folder(path: str | os.PathLike, root: str | os.PathLike) -> Path | None:
    """Where `path` really leads (links resolved) when that is outside folder `root`, else None."""
    real = Path(os.path.realpath(path))
    base = Path(os.path.realpath(root))
    return None if real == base or base in real.parents else real


def _children(x: Any) -> list | None:
    if isinstance(x, dict):
        return [*x.keys(), *x.values()]
    if isinstance(x, (list, tuple, set, frozenset)):
        return list(x)
    dtype = getattr(x, "dtype", None)
    if dtype is not None and getattr(dtype, "kind", "") == "O" and hasattr(x, "flat"):
        return list(x.flat)
    return None


_TOO_MANY = "it expands to more than {} values (repeated references or aliases multiply what it holds)"


def structure_problem(obj: Any, max_depth: int = MAX_DEPTH, max_values: int | None = None) -> str | None:
    """None, or what is wrong with a loaded structure (see the module doc) as a phrase: `it is nested deeper
    than 64 levels`, `it holds itself`, `it expands to more than N values`. Values are counted once per
    use (a shared or aliased container as often as it is referenced); the walk visits each container once."""
    top = _children(obj)
    if top is None:
        return None
    limit = float("inf") if max_values is None else max_values
    done: dict[int, int] = {}
    active = {id(obj)}
    stack: list[list] = [[obj, top, 0, 1]]  # container, its children, next child, values so far
    while stack:
        frame = stack[-1]
        node, children, i, _ = frame
        if i == len(children):
            stack.pop()
            active.discard(id(node))
            done[id(node)] = frame[3]
            if stack:
                stack[-1][3] += frame[3]
            if frame[3] > limit or (stack and stack[-1][3] > limit):
                return _TOO_MANY.format(max_values)
            continue
        frame[2] = i + 1
        child = children[i]
        key = id(child)
        if key in done:
            frame[3] += done[key]
        elif key in active:
            return "it holds itself (a value that contains itself, which never ends when expanded)"
        else:
            grand = _children(child)
            if grand is None:
                frame[3] += 1
            else:
                if len(stack) >= max_depth:
                    return f"it is nested deeper than {max_depth} levels"
                active.add(key)
                stack.append([child, grand, 0, 1])
                continue
        if frame[3] > limit:
            return _TOO_MANY.format(max_values)
    return None


__all__ = ["CLIP_CHARS", "ESCAPE_ERRORS", "EXCERPT_CHARS", "MAX_DEPTH", "clip", "excerpt", "outside_folder",
           "structure_problem"]
