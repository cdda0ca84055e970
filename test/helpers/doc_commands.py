"""The shell commands a page of the docs tells its reader to type: one entry per command of its ``bash`` / ``sh``
code blocks (continued lines joined, comments dropped, several commands of one line split at ``;``/``&&``), with
the page's line and the section (``##`` heading) it stands under."""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path

FENCE_RE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
HEADING_RE = re.compile(r"^## (.*)$", re.M)


@dataclass(frozen=True)
class Command:
    """One command of a page: its words (as the shell splits them), where it stands, and its code block's index."""

    words: tuple[str, ...]
    line: int
    section: str
    block: int

    @property
    def dev_argv(self) -> list[str] | None:
        """The arguments after ``./dev`` (``None`` for a command that is not ``./dev``'s)."""
        return list(self.words[self.words.index("./dev") + 1:]) if "./dev" in self.words else None

    def __str__(self) -> str:
        return " ".join(self.words)


def shell_commands(page: Path) -> list[Command]:
    """Every command of the page's shell code blocks, in reading order (``$s`` of a loop read as ``0``)."""
    text = page.read_text(encoding="utf-8")
    headings = [(m.start(), m.group(1)) for m in HEADING_RE.finditer(text)]
    found = []
    for index, block in enumerate(FENCE_RE.finditer(text)):
        if block.group(1) not in ("", "bash", "sh"):
            continue
        section = next((h for start, h in reversed(headings) if start < block.start()), "")
        first_line = text.count("\n", 0, block.start()) + 2
        for offset, line in enumerate(block.group(2).replace("\\\n", " ").splitlines()):
            line = re.sub(r"(^|\s)#.*", "", line).replace("$s", "0")
            lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|")
            lexer.whitespace_split = True
            words: list[str] = []
            for token in [*lexer, ";"]:
                if token and set(token) <= set(";&|"):  # the end of one command
                    if words:
                        found.append(Command(tuple(words), first_line + offset, section, index))
                    words = []
                else:
                    words.append(token)
    return found
