"""The docs stay true: every relative link in the README, the pages under docs/ and the package READMEs
points at a file of the repository (and, when it names one, at a heading of that page, by GitHub's
anchor rules), and every flag the docs give a `nak` subcommand is one `nak <subcommand> --help` lists.

Flags are read from code: a code block or code span holding a `nak <subcommand> …` command line
(also `cargo run --release -- <subcommand> …`) must use only that subcommand's flags; a code span that is
a bare flag (`--ui ADDR`) must be a flag of some nak subcommand, unless it is one of the few flags of
other tools the docs name (FOREIGN_FLAGS)."""

from __future__ import annotations

import re
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote

import pytest

from conftest import ROOT


def pages() -> list[Path]:
    """Every page a reader of the repository is sent to."""
    found = [ROOT / "README.md", ROOT / "training" / "README.md", ROOT / "clients" / "python" / "README.md"]
    return found + sorted((ROOT / "docs").rglob("*.md"))


# Flags of other tools that the docs name in bare code spans, and the tool each belongs to.
FOREIGN_FLAGS = {
    "--bench": "cargo bench",
    "--device": "docker run",
    "--baseline": "criterion (cargo bench)",
    "--save-baseline": "criterion (cargo bench)",
}
# Pages about another tool: their bare flags are that tool's (their `nak …` command lines are checked).
OTHER_TOOL_PAGES = {"training/README.md": "scripts/nak-train", "docs/your-own-organ.md": "scripts/nak-organ"}

FENCE = re.compile(r"^\s*(```|~~~)")
# A code span: a run of backticks, its content (not across a blank line), the same run again.
SPAN = re.compile(r"(?<!`)(`+)(?!`)((?:(?!\n[ \t]*\n).)+?)(?<!`)\1(?!`)", re.DOTALL)
LINK = re.compile(r"!?\[([^\]]*)\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^(#{1,6})\s+(.+?)\s*#*\s*$")
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
# `nak <words…>` or `cargo run [--release] [--bin nak] -- <words…>`; not nak_client, nak-train, nak.predict.
INVOCATION = re.compile(r"(?:(?<![\w.-])nak|cargo run(?: --release)?(?: --bin nak)? --)[ \t]+(?P<rest>\S.*)")
# Where a command line ends: a pipe, a list or a redirection (`|` inside a word, as in `unary|stream`, is
# a value, not a pipe).
COMMAND_END = re.compile(r"\s(?:\|\|?|&&|;|>|2>)\s|;")
COMMENT = re.compile(r"(?:^|\s)#(?:\s.*)?$")


@dataclass
class Markdown:
    """A page split into what is rendered as text and what is code."""

    path: Path
    prose: str
    code_blocks: list[str]
    code_spans: list[str]
    headings: list[str]


def parse(path: Path) -> Markdown:
    blocks: list[str] = []
    headings: list[str] = []
    text_lines: list[str] = []
    block: list[str] | None = None
    for line in path.read_text().split("\n"):
        if FENCE.match(line):
            if block is None:
                block = []
            else:
                blocks.append("\n".join(block))
                block = None
            text_lines.append("")
            continue
        if block is not None:
            block.append(line)
            continue
        heading = HEADING.match(line)
        if heading:
            headings.append(heading.group(2))
        text_lines.append(line)
    text = "\n".join(text_lines)
    spans = [m.group(2).strip() for m in SPAN.finditer(text)]
    prose = SPAN.sub("", text)
    return Markdown(path, prose, blocks, spans, headings)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: its text as rendered (links as their text, no code backticks or
    emphasis stars), lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = text.replace("`", "").replace("*", "")
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


def anchors(page: Markdown) -> set[str]:
    seen: dict[str, int] = {}
    found = set()
    for heading in page.headings:
        base = slug(heading)
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f"{base}-{count}")
    return found


def link_problems(path: Path, root: Path = ROOT) -> list[str]:
    """Relative links of `path` that lead nowhere: a missing file, a file outside the repository, or an
    anchor no heading of the target page has."""
    page = parse(path)
    problems = []
    for match in LINK.finditer(page.prose):
        target = match.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("//"):
            continue  # an address on the web, not a file here
        where = f"{path.relative_to(root)}: link to {target}"
        file_part, _, anchor = unquote(target).partition("#")
        resolved = (path.parent / file_part).resolve() if file_part else path.resolve()
        if not resolved.is_relative_to(root.resolve()):
            problems.append(f"{where}: outside the repository")
            continue
        if not resolved.exists():
            problems.append(f"{where}: no such file")
            continue
        if anchor and resolved.suffix == ".md" and anchor not in anchors(parse(resolved)):
            problems.append(f"{where}: {resolved.relative_to(root.resolve())} has no heading with anchor #{anchor}")
    return problems


Commands = dict[tuple[str, ...], set[str]]
"""Each subcommand (as its words: ("serve",), ("dataset", "join")) and the flags its --help lists; the
top level, (), holds the flags every subcommand takes."""


def help_text(nak_binary: Path, words: tuple[str, ...]) -> str:
    command = [str(nak_binary), *words, "--help"]
    return subprocess.run(command, capture_output=True, text=True, check=True).stdout


def parse_help(text: str) -> tuple[set[str], list[str]]:
    """The flags (with their aliases) and the subcommands a clap help text lists."""
    flags: set[str] = set()
    subcommands: list[str] = []
    section = ""
    for line in text.split("\n"):
        if re.match(r"^\S.*:$", line):
            section = line
            continue
        if section.startswith("Commands"):
            command = re.match(r"^\s+([a-z][a-z0-9-]*)\s", line + " ")
            if command and command.group(1) != "help":
                subcommands.append(command.group(1))
        option = re.match(r"^\s+(?:-[A-Za-z0-9], )?(--[a-z0-9][a-z0-9-]*)", line)
        if option:
            flags.add(option.group(1))
        for aliases in re.findall(r"\[aliases: ([^\]]+)\]", line):
            flags.update(FLAG.findall(aliases))
    return flags, subcommands


def read_commands(nak_binary: Path) -> Commands:
    commands: Commands = {}
    pending: list[tuple[str, ...]] = [()]
    while pending:
        words = pending.pop()
        flags, subcommands = parse_help(help_text(nak_binary, words))
        commands[words] = flags
        pending.extend((*words, sub) for sub in subcommands)
    return commands


def command_lines(snippet: str) -> Iterator[str]:
    """The lines of a code block or span, continuation lines (ending in a backslash) joined, without
    shell (or TOML, or Python) comments."""
    for line in re.sub(r"\\\n", " ", snippet).split("\n"):
        yield COMMENT.sub("", line)


def invocations(line: str) -> Iterator[tuple[list[str], str]]:
    """Each `nak …` command on a line, as its words up to the first flag and the rest of the command."""
    for match in INVOCATION.finditer(line):
        rest = COMMAND_END.split(match.group("rest"), maxsplit=1)[0]
        words = rest.split()
        leading = []
        for word in words:
            if not re.fullmatch(r"[a-z][a-z0-9-]*", word):
                break
            leading.append(word)
        yield leading, rest


def shorten(line: str) -> str:
    line = " ".join(line.split())
    return line if len(line) <= 100 else line[:97] + "..."


def flag_problems(path: Path, commands: Commands, root: Path = ROOT) -> list[str]:
    """Flags `path` gives a nak subcommand that its --help does not list."""
    page = parse(path)
    every_flag = set().union(*commands.values())
    problems = []
    snippets = page.code_blocks + page.code_spans
    for snippet in snippets:
        for line in command_lines(snippet):
            for leading, rest in invocations(line):
                # The longest run of leading words that names a subcommand: `dataset join`, then `serve`.
                words: tuple[str, ...] = ()
                for word in leading:
                    if (*words, word) not in commands:
                        break
                    words = (*words, word)
                flags = FLAG.findall(rest)
                if not words:
                    if flags and leading:
                        problems.append(
                            f"{path.relative_to(root)}: `nak {leading[0]}` is no nak subcommand: {shorten(line)}"
                        )
                    continue
                allowed = commands[words] | commands[()]
                for flag in flags:
                    if flag not in allowed:
                        name = " ".join(words)
                        problems.append(f"{path.relative_to(root)}: `nak {name}` has no {flag}: {shorten(line)}")
    if path.relative_to(root).as_posix() in OTHER_TOOL_PAGES:
        return problems
    for span in page.code_spans:
        if span.startswith("--"):
            for flag in FLAG.findall(span):
                if flag not in every_flag and flag not in FOREIGN_FLAGS:
                    problems.append(f"{path.relative_to(root)}: no nak subcommand has {flag}: `{span}`")
    return problems


@pytest.fixture(scope="module")
def commands(nak_binary: Path) -> Commands:
    return read_commands(nak_binary)


def test_the_help_lists_the_subcommands_and_flags_the_checks_rely_on(commands: Commands) -> None:
    assert "--prior-backend" in commands[("serve",)]
    assert "--shard" in commands[("datagen",)]
    assert ("dataset", "join") in commands and ("mesh", "info") in commands


@pytest.mark.parametrize("path", pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_link_leads_somewhere(path: Path) -> None:
    problems = link_problems(path)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("path", pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_flag_named_for_nak_is_one_it_takes(path: Path, commands: Commands) -> None:
    problems = flag_problems(path, commands)
    assert not problems, "\n".join(problems)


def test_the_checks_catch_a_missing_file_a_missing_heading_and_a_stale_flag(tmp_path: Path) -> None:
    """The checks themselves, on a made-up page and a made-up --help, so that a check that silently
    passes everything fails here."""
    (tmp_path / "other.md").write_text("# Other page\n\n## The prior — Kelvinlet (`ε`)\n\n## Twice\n\n## Twice\n")
    page = tmp_path / "page.md"
    page.write_text(
        "# Page\n\n"
        "[ok](other.md) [ok](other.md#the-prior--kelvinlet-ε) [ok](other.md#twice-1) [ok](#page)\n"
        "[gone](missing.md) [gone](other.md#no-such-heading) [out](../../outside.md) [web](https://example.org/x)\n"
        "`[not a link](missing-too.md)`\n\n"
        "Run `nak serve --listen ADDR --gone` or `--ui ADDR` or `--nowhere` or `--device /dev/x`.\n\n"
        "```sh\n"
        "nak serve --listen 127.0.0.1:0 \\\n"
        "          --stale-flag   # a comment --not-a-flag\n"
        "cargo run --release -- predict --model kelvinlet --old | grep --count x\n"
        "nak dataset join --out DATA --shard 1/2\n"
        "nak train --config C\n"
        "```\n"
    )
    problems = link_problems(page, root=tmp_path.parent)
    assert [p.split(": link to ")[1] for p in problems] == [
        "missing.md: no such file",
        f"other.md#no-such-heading: {tmp_path.name}/other.md has no heading with anchor #no-such-heading",
        "../../outside.md: outside the repository",
    ], problems

    commands: Commands = {
        (): {"--help", "--log-format"},
        ("serve",): {"--listen", "--ui"},
        ("predict",): {"--model"},
        ("dataset",): set(),
        ("dataset", "join"): {"--out"},
    }
    problems = flag_problems(page, commands, root=tmp_path)
    expected = [
        "`nak serve` has no --gone",
        "no nak subcommand has --nowhere",
        "`nak serve` has no --stale-flag",
        "`nak predict` has no --old",
        "`nak dataset join` has no --shard",
        "`nak train` is no nak subcommand",
    ]
    assert len(problems) == len(expected), problems
    for message in expected:
        assert any(message in p for p in problems), (message, problems)


def test_slugs_follow_github() -> None:
    assert slug("3. The Kelvinlet prior") == "3-the-kelvinlet-prior"
    assert slug("Ground truth (Mooney–Rivlin)") == "ground-truth-mooneyrivlin"
    assert slug("The path of one `Predict` call") == "the-path-of-one-predict-call"
    assert slug("Kubernetes (`docker/k8s`)") == "kubernetes-dockerk8s"
    assert slug("[Linked](x.md) *emphasis* snake_case") == "linked-emphasis-snake_case"
