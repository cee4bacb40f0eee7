"""The README stays a user's guide whose commands run.

Every ``streaklab COMMAND`` in a fenced code block of README.md must name a real subcommand of
:data:`streaklab.cli.COMMANDS` (``streaklab bench NAME``: a real benchmark of
:data:`streaklab.commands.bench.BENCHMARKS`), and every ``--flag`` given to it must be an option
of that subcommand's own parser, built the way ``streaklab`` builds it.  The README is at most
:data:`README_MAX_LINES` lines: measurement history belongs in docs/history.md.
"""
import argparse
import importlib
import re
import shlex
from pathlib import Path

from streaklab.cli import COMMANDS
from streaklab.commands.bench import BENCHMARKS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
README_MAX_LINES = 250

_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
_SEPARATORS = {"|", "||", "&&", ";", "&"}


def code_block_lines(text: str) -> list[str]:
    """The lines of every fenced code block, backslash continuations joined, comments cut."""
    lines = []
    for block in _FENCE.findall(text):
        for line in block.replace("\\\n", " ").splitlines():
            lines.append(line.split("#", 1)[0])
    return lines


def streaklab_calls(text: str) -> list[list[str]]:
    """Each ``streaklab ...`` call in the code blocks of ``text``, as its words after ``streaklab``."""
    calls = []
    for line in code_block_lines(text):
        words = shlex.split(line)
        for i, word in enumerate(words):
            if word == "streaklab":
                call = []
                for w in words[i + 1:]:
                    if w in _SEPARATORS:
                        break
                    call.append(w)
                calls.append(call)
    return calls


def _options(module_name: str, prog: str) -> set[str]:
    parser = argparse.ArgumentParser(prog=prog)
    importlib.import_module(module_name).add_arguments(parser)
    return {s for action in parser._actions for s in action.option_strings}


def command_problems(text: str) -> list[str]:
    """One line per ``streaklab`` call in the code blocks of ``text`` that would not parse."""
    problems = []
    for call in streaklab_calls(text):
        shown = " ".join(["streaklab", *call])
        if not call or call[0] not in COMMANDS:
            problems.append(f"{shown}: no such subcommand")
            continue
        name, rest = call[0], call[1:]
        module, prog = COMMANDS[name][0], f"streaklab {name}"
        if name == "bench":
            if not rest or rest[0] not in BENCHMARKS:
                problems.append(f"{shown}: no such benchmark")
                continue
            module, prog, rest = f"streaklab.bench.{rest[0]}", f"{prog} {rest[0]}", rest[1:]
        known = _options(module, prog)
        for word in rest:
            if word.startswith("-") and word not in ("-", "--"):
                flag = word.split("=", 1)[0]
                if flag not in known:
                    problems.append(f"{shown}: {prog} has no option {flag}")
    return problems


def test_readme_is_at_most_250_lines():
    n_lines = len(README.read_text(encoding="utf-8").splitlines())
    assert n_lines <= README_MAX_LINES, f"README.md has {n_lines} lines (at most {README_MAX_LINES})"


def test_readme_commands_are_real_subcommands_with_real_options():
    text = README.read_text(encoding="utf-8")
    calls = streaklab_calls(text)
    named = {call[0] for call in calls if call}
    assert {"capture", "reconstruct", "decompose", "report", "verify"} <= named
    assert command_problems(text) == []


def test_the_check_names_a_wrong_subcommand_benchmark_and_option():
    bad = (
        "intro\n\n```\n"
        "streaklab capture --config sim --out run.zarr --simulate     # fine\n"
        "streaklab decompse cube.zarr --out r.zarr\n"
        "streaklab decompose cube.zarr --out r.zarr --worker 2\n"
        "streaklab bench speeed\n"
        "streaklab bench speed --photons 100 --nsr=0.1 --pixels 10\n"
        "streaklab verify \\\n    --mark-for-resume --force run.zarr\n"
        "```\n\n`streaklab inline --not-checked` outside a block\n"
    )
    assert command_problems(bad) == [
        "streaklab decompse cube.zarr --out r.zarr: no such subcommand",
        "streaklab decompose cube.zarr --out r.zarr --worker 2: streaklab decompose has no option --worker",
        "streaklab bench speeed: no such benchmark",
        "streaklab bench speed --photons 100 --nsr=0.1 --pixels 10: "
        "streaklab bench speed has no option --pixels",
        "streaklab verify --mark-for-resume --force run.zarr: streaklab verify has no option --force",
    ]


DECOMPOSITION_DOC = ROOT / "docs" / "decomposition.md"
_STAGE_ROW = re.compile(r"^\| `([a-z_]+)` \|")


def documented_stages(text: str) -> list[list[str]]:
    """The stage names of each table of the *Stages* section of docs/decomposition.md, in order."""
    section = text.split("\n## Stages\n", 1)[1].split("\n## ", 1)[0]
    tables, current = [], None
    for line in section.splitlines():
        if line.startswith("| stage |"):
            current = []
            tables.append(current)
        elif current is not None and line.startswith("|"):
            match = _STAGE_ROW.match(line)
            if match:
                current.append(match.group(1))
        else:
            current = None
    return tables


def test_the_documented_stage_lists_are_the_code_s():
    from decomposition.api import STAGES
    tables = documented_stages(DECOMPOSITION_DOC.read_text(encoding="utf-8"))
    assert tables == [[s.name for s in STAGES]]


def test_the_stage_check_sees_a_swapped_or_missing_stage():
    text = ("intro\n\n## Stages\n\n| stage | what |\n|---|---|\n| `prepare` | p |\n| `refit` | r |\n| `label` | l |\n\n"
            "| stage | what |\n|---|---|\n| `prepare` | p |\n\n## Next\n| `other` | x |\n")
    assert documented_stages(text) == [["prepare", "refit", "label"], ["prepare"]]
