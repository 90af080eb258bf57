"""Every command output shown in README.md and docs/*.md, regenerated and compared: docs that cannot go stale.

Usage::

    python scripts/doc_outputs.py --check            # run every marked command, compare, exit 1 with a diff
    python scripts/doc_outputs.py --write            # run them and rewrite the blocks with what they print
    python scripts/doc_outputs.py --check docs/tutorial.md   # one file
    python scripts/doc_outputs.py --list             # the marked blocks, nothing run

Marking a block
---------------
A fenced block (three backticks) that shows what a command prints is marked by an HTML comment on the line just
before its opening fence (invisible in the rendered page). Four markers:

``<!-- magkf-output: COMMAND -->``
    The block is exactly what ``COMMAND`` prints (standard output and standard error, interleaved as on a
    terminal). The command is not shown in the block; the text around it says what it is.
``<!-- magkf-session -->``
    The block is a terminal session: each line that starts with ``$ `` is a command, and the lines after it, up
    to the next ``$ `` line, are what it prints. The commands are kept; their outputs are replaced.
``<!-- magkf-setup -->``
    The block (Python when its fence says ``python``, else shell) is run as it is shown, and its output is not
    compared: it makes the inputs the commands read (a simulated log written in an autopilot's format, say).
    The setup blocks of a file run first, in their order, before any of its other blocks, so that a page may
    show a command on a file it makes further down.
``<!-- magkf-example: REASON -->``
    The block looks like a session but is not regenerated, because its input is not shipped with magkf (a
    user's own ROS bag, for instance); REASON says so. ``--check`` counts these, and refuses a block with
    ``$ `` lines that carries no marker at all, so that nothing output-like is left out silently.

A block whose command ends in an internal error of magkf is reported and never written: a defect is not a
documented output.

An abridged output shows its filter in the command itself (``$ magkf calibrate flight.bin -o c.json --quiet |
head -6``): what is shown is then exactly what that command line prints. Commands run through ``bash`` with
``set -o pipefail`` off, so ``| head`` may close the pipe early.

Where the commands run
----------------------
Each Markdown file gets a fresh temporary folder laid out as the repository root is in CI: ``data``, ``docs`` and
``scripts`` link to the repository's, and ``../shared`` to the shared folder beside the repository (as CI lays
it), so ``data/example_drive.csv`` and ``../shared/data/real/...`` work and every output lands in the temporary
folder. The blocks of one file run in order in its folder, so a later block may read what an earlier one wrote.
``magkf`` and ``python`` are this interpreter's (its ``bin`` folder first on ``PATH``); ``TZ=UTC``, ``LC_ALL=C.UTF-8``,
``PYTHONHASHSEED=0``, and standard input is empty.

What is normalised before comparing (and only this)
---------------------------------------------------
Figures that change from run to run although nothing changed are replaced, in the shown and in the produced
text alike, by a placeholder before they are compared. ``--write`` writes what the commands printed, but only
into blocks that differ after this: a block whose run time alone changed is left as it is.

1. a run's wall time and speed: ``60000 epochs in 0.69 s (86,363 epochs/s)`` -> ``60000 epochs in <s> s
   (<rate> epochs/s)`` (the epoch count is kept);
2. a Dask worker's port: ``tls://127.0.0.1:39771`` -> ``tls://127.0.0.1:<port>``;
3. peak memory in megabytes on a ``peak memory`` line (``207 MB``, ``limit 12638 MB``) -> ``<MB> MB``;
4. the temporary folder's own path, where a command prints an absolute path -> ``<tmp>``;
5. spaces at the end of a line (Markdown editors strip them).

Residuals, parameters, standard deviations, epoch counts, statuses, p-values and every word are compared as
printed: a changed figure fails the check.
"""

from __future__ import annotations

import argparse
import difflib
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FILES = ["README.md", "docs/*.md"]
TIMEOUT_S = 600
MARKER = re.compile(r"^<!--\s*magkf-(output|session|setup|example)(?::\s*(.*?))?\s*-->\s*$")
FENCE = re.compile(r"^(`{3,})(.*)$")
PROMPT = "$ "
INTERNAL_ERROR = "magkf: internal error"

NORMALISATIONS = [
    (re.compile(r"(\d+ epochs) in [\d.]+ s \([\d,.]+ epochs/s\)"), r"\1 in <s> s (<rate> epochs/s)"),
    (re.compile(r"((?:tcp|tls)://127\.0\.0\.1):\d+"), r"\1:<port>"),
    (re.compile(r"(?m)^(.*peak memory.*)$"), lambda m: re.sub(r"\b\d+ MB\b", "<MB> MB", m.group(1))),
    (re.compile(r"[ \t]+$", re.MULTILINE), ""),
]


@dataclass
class Block:
    """A marked fenced block of a Markdown file.

    Attributes
    ----------
    kind : str
        ``output``, ``session``, ``setup`` or ``example`` (the marker), or ``unmarked`` for a block with ``$ ``
        lines and no marker.
    argument : str
        The marker's text after the colon: the command of an ``output`` block, the reason of an ``example``.
    info : str
        The opening fence's info string (``python``, ``bash`` or empty).
    first, last : int
        Line numbers (0-based) of the first and the last line of the block's body; ``last < first`` when it is
        empty.
    body : list of str
        The lines between the fences.
    """

    kind: str
    argument: str
    info: str
    first: int
    last: int
    body: list[str] = field(default_factory=list)


def parse_blocks(text: str) -> list[Block]:
    """The marked blocks of Markdown ``text`` (and the unmarked ones that show ``$ `` lines), in order.

    Parameters
    ----------
    text : str
        The file's text.

    Returns
    -------
    list of Block

    Raises
    ------
    ValueError
        A marker not followed by a fence on the next line, or a fence never closed (with the line number).
    """
    lines = text.split("\n")
    blocks, i = [], 0
    while i < len(lines):
        marker = MARKER.match(lines[i])
        if marker and not (i + 1 < len(lines) and FENCE.match(lines[i + 1])):
            raise ValueError(f"line {i + 1}: a magkf-{marker.group(1)} marker must be followed by a fenced block")
        opening = FENCE.match(lines[i + 1]) if marker else FENCE.match(lines[i])
        if opening is None:
            i += 1
            continue
        start = i + 2 if marker else i + 1
        end = _closing_fence(lines, start, opening.group(1))
        body = lines[start:end]
        kind = marker.group(1) if marker else "unmarked"
        if marker or any(line.startswith(PROMPT) for line in body):
            argument = (marker.group(2) or "") if marker else ""
            blocks.append(Block(kind, argument, opening.group(2).strip(), start, end - 1, body))
        i = end + 1
    return blocks


def _closing_fence(lines: list[str], start: int, fence: str) -> int:
    """The line number of the fence that closes a block opened by ``fence`` whose body starts at ``start``."""
    for j in range(start, len(lines)):
        if lines[j].strip() == fence:
            return j
    raise ValueError(f"line {start}: a fenced block is never closed")


def session_commands(body: list[str]) -> list[str]:
    """The commands of a session block: its ``$ `` lines without the prompt."""
    return [line[len(PROMPT) :] for line in body if line.startswith(PROMPT)]


def session_body(commands: list[str], outputs: list[str]) -> list[str]:
    """A session block's lines: each command after its prompt, then what it printed."""
    lines = []
    for command, output in zip(commands, outputs, strict=True):
        lines.append(PROMPT + command)
        lines.extend(output_lines(output))
    return lines


def output_lines(output: str) -> list[str]:
    """A command's output as block lines (no final empty line)."""
    return output.rstrip("\n").split("\n") if output.strip() else []


def normalise(text: str, tmp: str | None = None) -> str:
    """``text`` with the figures that vary between identical runs replaced (the rules in this module's
    docstring); ``tmp`` is the temporary folder's path, replaced by ``<tmp>``."""
    if tmp:
        text = text.replace(tmp, "<tmp>")
    for pattern, replacement in NORMALISATIONS:
        text = pattern.sub(replacement, text)
    return text


def compare(shown: list[str], produced: list[str], name: str, tmp: str | None = None) -> str:
    """A unified diff of a block as shown against as produced, after ``normalise``; empty when they agree.

    Parameters
    ----------
    shown, produced : list of str
        The block's lines in the Markdown file, and the lines regenerated.
    name : str
        Where the block is (file and line), for the diff's header.
    tmp : str, optional
        The temporary folder's path, normalised away.
    """
    a = normalise("\n".join(shown)).split("\n")
    b = normalise("\n".join(produced), tmp).split("\n")
    if a == b:
        return ""
    return "\n".join(difflib.unified_diff(a, b, f"{name} (shown)", f"{name} (produced)", lineterm=""))


class Workspace:
    """A temporary folder laid out as the repository root in CI, where one Markdown file's commands run."""

    def __init__(self):
        self._dir = tempfile.TemporaryDirectory(prefix="magkf-docs-")
        base = Path(self._dir.name)
        self.path = base / "repo"
        self.path.mkdir()
        for name in ("data", "docs", "scripts"):
            (self.path / name).symlink_to(ROOT / name)
        shared = ROOT.parent / "shared"
        if shared.is_dir():
            (base / "shared").symlink_to(shared)
        bin_dir = str(Path(sys.executable).parent)
        self.env = {
            **os.environ,
            "PATH": bin_dir + os.pathsep + os.environ.get("PATH", ""),
            "TZ": "UTC",
            "LC_ALL": "C.UTF-8",
            "PYTHONHASHSEED": "0",
        }

    def run(self, command: str) -> str:
        """What ``command`` prints (standard output and error interleaved), run by bash in the folder."""
        proc = subprocess.run(
            ["bash", "-c", command],
            cwd=self.path,
            env=self.env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            timeout=TIMEOUT_S,
        )
        return proc.stdout

    def run_setup(self, block: Block) -> None:
        """Run a setup block as shown; raise RuntimeError with its output when it fails."""
        script = "\n".join(block.body)
        if block.info in ("python", "py"):
            argv = [sys.executable, "-c", script]
        else:
            argv = ["bash", "-e", "-c", script]
        proc = subprocess.run(
            argv, cwd=self.path, env=self.env, stdin=subprocess.DEVNULL, capture_output=True, text=True
        )
        if proc.returncode != 0:
            raise RuntimeError(f"setup block at line {block.first} failed:\n{proc.stdout}{proc.stderr}")

    def close(self) -> None:
        self._dir.cleanup()


def regenerate(block: Block, workspace: Workspace) -> list[str]:
    """The body of ``block`` as its commands print it now (a setup block is run and kept as it is)."""
    if block.kind == "output":
        return output_lines(workspace.run(block.argument))
    if block.kind == "session":
        commands = session_commands(block.body)
        return session_body(commands, [workspace.run(c) for c in commands])
    if block.kind == "setup":
        workspace.run_setup(block)
    return block.body


def process_file(path: Path, write: bool) -> tuple[list[str], dict]:
    """Regenerate the marked blocks of one Markdown file; rewrite it with ``write``.

    Returns
    -------
    problems : list of str
        A diff per block that differs (when checking), and a line per unmarked block with ``$ `` lines.
    counts : dict
        Blocks of each kind.
    """
    text = path.read_text()
    blocks = parse_blocks(text)
    counts = {kind: sum(b.kind == kind for b in blocks) for kind in ("output", "session", "setup", "example")}
    rel = path.relative_to(ROOT)
    problems = [
        f"{rel}:{b.first}: a block with '$ ' lines and no magkf-output/session/example marker"
        for b in blocks
        if b.kind == "unmarked"
    ]
    runnable = [b for b in blocks if b.kind == "setup"] + [b for b in blocks if b.kind in ("output", "session")]
    if not runnable:
        return problems, counts
    workspace = Workspace()
    try:
        new_bodies, differences = _regenerate_all(runnable, workspace, str(rel))
    finally:
        workspace.close()
    problems.extend(d for d in differences if not (write and d.startswith("---")))  # written, not a problem
    if write:
        path.write_text(_replace_bodies(text, runnable, new_bodies))
    return problems, counts


def _regenerate_all(blocks: list[Block], workspace: Workspace, rel: str) -> tuple[dict, list[str]]:
    """Each block's new body (the shown one where it differs only by what ``normalise`` replaces, or where its
    command ended in an internal error) by its first line, and the problems: a diff per block that differs,
    a line per internal error."""
    new_bodies, problems = {}, []
    for block in blocks:
        produced = regenerate(block, workspace)
        diff = (
            "" if block.kind == "setup" else compare(block.body, produced, f"{rel}:{block.first}", str(workspace.path))
        )
        new_bodies[block.first] = produced if diff else block.body  # no churn of run times alone
        if diff:
            problems.append(diff)
        if any(INTERNAL_ERROR in line for line in produced):
            problems.append(f"{rel}:{block.first}: a command ended in an internal error of magkf (not written)")
            new_bodies[block.first] = block.body
    return new_bodies, problems


def _replace_bodies(text: str, blocks: list[Block], bodies: dict) -> str:
    """``text`` with each block's body replaced by ``bodies[block.first]`` (from the last block up)."""
    lines = text.split("\n")
    for block in sorted(blocks, key=lambda b: b.first, reverse=True):
        lines[block.first : block.last + 1] = bodies[block.first]
    return "\n".join(lines)


def markdown_files(names: list[str]) -> list[Path]:
    """The files named (relative to the repository root), or README.md and docs/*.md."""
    if names:
        return [(ROOT / n).resolve() for n in names]
    return [p for pattern in FILES for p in sorted(ROOT.glob(pattern))]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--check", action="store_true", help="compare; exit 1 with a diff when a block differs")
    mode.add_argument("--write", action="store_true", help="rewrite the blocks with what the commands print")
    mode.add_argument("--list", action="store_true", help="list the marked blocks; run nothing")
    parser.add_argument("files", nargs="*", help="Markdown files (default: README.md and docs/*.md)")
    args = parser.parse_args(argv)
    failed, totals = False, {}
    for path in markdown_files(args.files):
        if args.list:
            for b in parse_blocks(path.read_text()):
                print(f"{path.relative_to(ROOT)}:{b.first} {b.kind} {b.argument}".rstrip())
            continue
        problems, counts = process_file(path, args.write)
        totals = {k: totals.get(k, 0) + v for k, v in counts.items()}
        for problem in problems:
            print(problem)
        failed |= bool(problems)
    if not args.list:
        summary = ", ".join(f"{n} {kind}" for kind, n in totals.items())
        verdict = "some differ or are unmarked" if failed else ("written" if args.write else "all as shown")
        print(f"doc outputs: {summary} block(s); {verdict}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
