"""How the console scripts report what a user got wrong: one line naming it and the fix, exit code 2."""
from __future__ import annotations

import sys

# What a user gets wrong (a path, an option, a task, a file of another kind); anything else is a bug and keeps
# its traceback.
USER_ERRORS = (FileNotFoundError, ValueError, KeyError)


def user_error(prog: str, exc: BaseException) -> int:
    """Print ``prog: error: <message>`` to stderr and return the exit code 2."""
    message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
    print(f"{prog}: error: {message}", file=sys.stderr)
    return 2


def first_line(text: str, limit: int = 160) -> str:
    """The first line of a library's error text, bounded (their messages run on for paragraphs); '?' if empty."""
    return (text.strip().splitlines() or ["?"])[0][:limit]
