"""The documented examples (README.md's code blocks, every command's --help Examples) as shell commands.

:func:`readme_examples` and :func:`help_examples` extract them as written;
:func:`run_examples` runs them in order with bash in one folder that stands
for the root of a clone (``perscli`` on PATH, sample_data/ and examples/ as
the repository has them and, when present, the real inputs of
../shared/data linked in by name, as a user who downloaded them would have
them), and returns what happened to each.

An example is *skipped* only when it names a file of ../shared/data that
is absent (a clone without the shared folder), when it is
:data:`EXPENSIVE` and expensive ones are not asked for, or when it reads a
file that only a skipped example makes; every other example must exit 0
and must not write an output that an earlier example wrote (outputs are
distinct, so that examples can be run in any order a reader picks without
clobbering each other).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: examples that cannot run here, with the reason (kept to a minimum: each is a documented exception)
NOT_RUN = {
    "--scheduler tcp://HOST:8786": "needs a running Dask scheduler at HOST",
}

#: inputs in the repository that name a shared input inside them (none: the Roman schedule is bundled)
REQUIRES: dict = {}

#: examples that run a whole study, plan the paper's, or search a frame for missing effects (diagnose): tens of
#: seconds to minutes each; run by the slow tests only
EXPENSIVE = (re.compile(r"perscli study (?!.*--dry-run)"), re.compile(r"perscli study .*--preset paper"),
             re.compile(r"perscli diagnose "))


def is_expensive(command: str) -> bool:
    """Whether an example runs a whole study, plans the paper's or runs diagnose: not seconds."""
    return any(p.search(command) for p in EXPENSIVE)

_OUTPUT_FLAGS = ("-o", "--output", "--plot", "--plots", "--write-psf", "--regions")


@dataclass
class Example:
    """One documented shell command."""

    source: str  # 'README.md:123' or 'perscli render --help'
    command: str

    def tokens(self) -> list:
        try:
            return shlex.split(self.command, comments=True)
        except ValueError:
            return self.command.split()

    def outputs(self) -> list:
        """Files the example writes (after -o, --plot, ...; '-' excluded; redirections)."""
        toks = self.tokens()
        out = []
        for k, tok in enumerate(toks):
            if tok in _OUTPUT_FLAGS and k + 1 < len(toks) and toks[k + 1] != "-":
                out.append(toks[k + 1])
            elif tok.startswith("--output=") or tok.startswith("--plot="):
                out.append(tok.split("=", 1)[1])
            elif tok == ">" and k + 1 < len(toks):
                out.append(toks[k + 1])
        return out


@dataclass
class Outcome:
    example: Example
    status: str  # 'ok', 'failed', 'skipped'
    reason: str = ""
    seconds: float = 0.0


def _logical_lines(lines):
    """Join backslash continuations."""
    buf = ""
    start = None
    for number, line in lines:
        if start is None:
            start = number
        stripped = line.rstrip()
        if stripped.endswith("\\"):
            buf += stripped[:-1].rstrip() + " "
            continue
        yield start, (buf + stripped.strip()).strip()
        buf, start = "", None
    if buf:
        yield start, buf.strip()


_PERSCLI = ("perscli", ".venv/bin/perscli")
#: commands that may start a documented pipeline feeding perscli
_FEEDERS = ("cat", "zcat", "gzip", "eval")


def _is_example(line: str) -> bool:
    """A shell line that runs perscli: it starts with perscli (after VAR=value assignments), or a
    pipeline or eval of a few shell commands runs it."""
    words = line.split()
    while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=\S*", words[0]):
        words = words[1:]
    if not words:
        return False
    if words[0] in _PERSCLI:
        return True
    return words[0] in _FEEDERS and re.search(r"(^|[|(\s])(\.venv/bin/)?perscli(\s|\)|$)", line) is not None


def readme_examples(path: Path = ROOT / "README.md") -> list:
    """Shell examples of README.md's indented and fenced (sh/bash/console/unlabelled) code blocks, in order."""
    lines = path.read_text().splitlines()
    blocks, current, fence = [], [], None
    for number, line in enumerate(lines, 1):
        if fence is not None:
            if line.strip().startswith("```"):
                if fence in ("", "sh", "bash", "shell", "console"):
                    blocks.append(current)
                current, fence = [], None
            else:
                current.append((number, line))
            continue
        if line.strip().startswith("```"):
            if current:
                blocks.append(current)
            fence = line.strip()[3:].strip().lower()
            current = []
            continue
        if line.startswith("    ") and line.strip():
            current.append((number, line[4:]))
        elif line.strip() == "" and current:
            current.append((number, ""))
        else:
            if current:
                blocks.append(current)
            current = []
    if current and fence is None:
        blocks.append(current)
    out = []
    for block in blocks:
        for number, text in _logical_lines([(n, t) for n, t in block if t.strip()]):
            text = text[2:] if text.startswith("$ ") else text
            if _is_example(text):
                out.append(Example(f"{path.name}:{number}", text))
    return out


def help_examples(command, name: str | None = None) -> list:
    """The lines of a click command's 'Examples:' block (its docstring), in order; for a group with
    subcommands (perscli pointings), its own then each subcommand's.

    ``name`` is the command line that shows the help ('perscli pointings plan'; default 'perscli NAME').
    """
    name = name or f"perscli {command.name}"
    doc = command.help or ""
    lines = doc.splitlines()
    out, inside = [], False
    block = []
    for number, line in enumerate(lines, 1):
        if line.strip() == "Examples:":
            inside = True
            continue
        if inside:
            if not line.strip():
                break
            block.append((number, line))
    for _, text in _logical_lines(block):
        if _is_example(text):
            out.append(Example(f"{name} --help", text))
    for sub, subcommand in getattr(command, "commands", {}).items():
        out += help_examples(subcommand, f"{name} {sub}")
    return out


def script_dir() -> Path:
    """The folder of the installed ``perscli`` script (the test's interpreter's)."""
    return Path(sys.executable).parent


def shared_files(shared: Path) -> dict:
    """{basename: path} of every file under ../shared/data (empty when the folder is absent)."""
    if not shared.is_dir():
        return {}
    return {p.name: p for p in shared.rglob("*") if p.is_file()}


def prepare_folder(folder: Path, shared: Path, bindir: Path, *, samples_at_top: bool = True) -> None:
    """The sample data, the examples folder, the shared inputs (links) and a .venv/bin/perscli link.

    ``folder`` stands for a clone, with nothing beside it: no example may reach
    outside the clone (the Roman schedule is bundled).  The shared inputs are
    linked by name, as a user who downloaded them (MAST's WFC3 ramps, Gaia
    chunks) would have them.  ``samples_at_top``: the sample files are also
    copied to the top; the documented examples run from a clone as it is.
    """
    folder.mkdir(parents=True, exist_ok=True)
    for p in (ROOT / "sample_data").iterdir():
        if p.is_file() and samples_at_top:
            shutil.copy(p, folder / p.name)
    shutil.copytree(ROOT / "sample_data", folder / "sample_data", dirs_exist_ok=True)
    shutil.copytree(ROOT / "examples", folder / "examples", dirs_exist_ok=True)
    for name, path in shared_files(shared).items():
        if not (folder / name).exists():
            os.symlink(path, folder / name)
    venv = folder / ".venv" / "bin"
    venv.mkdir(parents=True, exist_ok=True)
    if not (venv / "perscli").exists():
        os.symlink(bindir / "perscli", venv / "perscli")


def run_examples(examples, folder: Path, *, shared: Path, bindir: Path | None = None, timeout: float | None = None,
                 known_shared=None, expensive: bool = True) -> list:
    """Run examples in order in ``folder`` (prepared with :func:`prepare_folder`); one Outcome each.

    Parameters
    ----------
    known_shared : iterable of str, optional
        Names of the shared inputs (whether present or not); by default the
        files of ../shared/data as documented in its README (gaia chunks,
        the Roman schedule, the WFC3 ramps).
    expensive : bool
        Also run the :data:`EXPENSIVE` examples (else they are skipped, with
        what they would have made).
    """
    bindir = bindir or script_dir()
    env = dict(os.environ)
    env["PATH"] = f"{bindir}{os.pathsep}{env.get('PATH', '')}"
    # examples that install something in ~ (shell completion) install it in the folder
    env["HOME"] = str(folder)
    present = shared_files(shared)
    known = set(known_shared or SHARED_NAMES) | set(present)
    written: dict = {}
    unavailable: set = set()
    outcomes = []
    for ex in examples:
        toks = ex.tokens()
        names = {Path(t).name for t in toks} | {t for t in toks}
        names |= {need for path, need in REQUIRES.items() if path in toks}
        skip = next((f"{reason}" for key, reason in NOT_RUN.items() if key in ex.command), None)
        if skip is None and not expensive and is_expensive(ex.command):
            skip = "a whole study, the paper's plan or diagnose (the slow tests run it)"
        if skip is None:
            missing = sorted(n for n in names if n in known and n not in present)
            if missing:
                skip = f"needs {', '.join(missing)} from ../shared/data"
        if skip is None:
            # a file made by a skipped example, or one inside a folder such an example makes
            blocked = sorted({t for t in toks if t not in ex.outputs() and
                              (t in unavailable or any(t.startswith(u.rstrip("/") + "/") for u in unavailable))}
                             | (names & unavailable - set(ex.outputs())))
            if blocked:
                skip = f"needs {', '.join(blocked)}, made by a skipped example"
        if skip is not None:
            unavailable.update(ex.outputs())
            outcomes.append(Outcome(ex, "skipped", skip))
            continue
        clash = [o for o in ex.outputs() if o in written]
        if clash:
            outcomes.append(Outcome(ex, "failed", f"writes {', '.join(clash)}, already written by "
                                                  f"{written[clash[0]].source}: outputs must be distinct"))
            continue
        t0 = time.perf_counter()
        proc = subprocess.run(["bash", "-o", "pipefail", "-c", ex.command], cwd=folder, env=env,
                              capture_output=True, text=True, timeout=timeout)
        seconds = time.perf_counter() - t0
        for o in ex.outputs():
            written[o] = ex
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["(no stderr)"])[-3:]
            outcomes.append(Outcome(ex, "failed", f"exit {proc.returncode}: {' | '.join(tail)}", seconds))
        else:
            outcomes.append(Outcome(ex, "ok", "", seconds))
    return outcomes


#: the inputs of ../shared/data that documented examples name (skipped, not failed, where absent)
SHARED_NAMES = ("Roman_WAS_obseq_11_1_23.fits", "145649.fits", "145650.fits", "ibh7a7lsq_raw.fits",
                "ibxy01aoq_raw.fits", "ibxy04s4q_raw.fits")


def report(outcomes) -> str:
    lines = []
    for o in outcomes:
        mark = {"ok": "ok  ", "failed": "FAIL", "skipped": "skip"}[o.status]
        lines.append(f"{mark} {o.seconds:6.1f}s  {o.example.source}: {o.example.command}"
                     + (f"\n      -> {o.reason}" if o.reason else ""))
    return "\n".join(lines)
