"""A Markdown page read as the documentation tests need it: its code spans, the names in them, its tables as
rows of cells, the text under a heading, and the command lines of its code blocks."""

import re
import shlex

SPAN = re.compile(r"`([^`\n]+)`")
# a name as a config writes one (a key, dotted or not; an option; a group's first part), not inside a path
# (`docs/data.md`, `/data/lego`), a number (`1.0e-4`) or a word joined by a hyphen (`bf16-mixed`)
NAME = re.compile(r"(?<![\w/.\-])[A-Za-z_]\w*(?:\.\w+)*")
HEADING = re.compile(r"(#+)\s+(.*)")
CODE_INDENT = "    "  # an indented code block's lines
LONGEST_CELL = 200  # characters: a table cell longer than this is a paragraph, which belongs in a page's text


def spans(text: str) -> list[str]:
    """The text of each code span (between backticks) of ``text``, in order."""
    return SPAN.findall(text)


def names(text: str) -> list[str]:
    """The names written in ``text``'s code spans: ``data.root=/x`` names ``data.root``, ``GROUP=a,b`` names
    ``GROUP``, ``a`` and ``b``."""
    return [name for span in spans(text) for name in NAME.findall(span)]


def tables(text: str) -> list[list[list[str]]]:
    """Each table of ``text`` as its rows (the header first, the ``|---|`` line left out), each row its cells'
    text, stripped."""
    found, rows = [], []
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            if not all(re.fullmatch(r":?-+:?", cell) for cell in cells):
                rows.append(cells)
        elif rows:
            found.append(rows)
            rows = []
    return found


def long_cells(text: str) -> list[str]:
    """The table cells of ``text`` longer than ``LONGEST_CELL`` characters."""
    return [cell for table in tables(text) for row in table for cell in row if len(cell) > LONGEST_CELL]


def section(text: str, title: str) -> str:
    """The text under the heading ``title`` (as written, backticks and all) to the next heading of its level or
    above; "" where ``text`` has no such heading."""
    lines, level, kept = text.splitlines(), None, []
    for line in lines:
        heading = HEADING.match(line)
        if level is None:
            if heading and heading[2].strip() == title:
                level = len(heading[1])
        elif heading and len(heading[1]) <= level:
            break
        else:
            kept.append(line)
    return "\n".join(kept)


def command_lines(text: str, programs: set[str]) -> list[list[str]]:
    """The command lines of ``text``'s code blocks (indented four spaces) that run one of ``programs``, each as its
    words (a comment left out; ``a && b``: each command apart)."""
    found = []
    for line in text.splitlines():
        if line.startswith(CODE_INDENT):
            command: list[str] = []
            for word in [*shlex.split(line, comments=True), "&&"]:
                if word != "&&":
                    command.append(word)
                    continue
                if command and command[0] in programs:
                    found.append(command)
                command = []
    return found
