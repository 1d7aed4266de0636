"""Every command quoted in README.md and docs/ (and benchmarks/reference/README.md), checked against the code, and
every relative link checked against the files and their headings:

    python tests/doc_commands.py            # one line per problem, exit 1 if any (tests/test_docs.py runs it)

A command is a line of a fenced code block, or an inline code span, that runs `python FILE ...` (or names a script of
the repository). Checks, in one process: the file exists; every --flag it gives is a flag of that script (of the
preset, for experiments/grid.py PRESET; of the script after `--`, for edits.py), read from its --help; where the
command has a placeholder (<run>, RUN_DIR, ...), the script's own parser (tyro.cli or argparse) accepts it with a
value in each placeholder, so that a required flag or argument left out is found (the script stops once parsed);
where it has none, it parses as a user would run it: pebble.py, prefppo.py and rime.py through their own parse_args,
make_env and check_args (every range check a run makes before any work), and experiments/grid.py as a --dry-run into
a temporary root. A grid preset's command runs as many seeds as the page says beside it: the "# N seeds" of its
comment, else the last count stated before it in its paragraph ("5 seeds", "three seeds", "seeds 1-5", a table's
"seeds" column; for a code block, the paragraph or table above it).
"""

import contextlib
import functools
import importlib
import io
import re
import runpy
import shlex
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "benchmarks" / "reference" / "README.md"]
ALGORITHMS = ("pebble.py", "prefppo.py", "rime.py")
NOT_HERE = ("trace_prefppo.py",)  # runs in the reference's environment with the reference's own flags
PLACEHOLDER = re.compile(r"<[^>]*>|^\.\.\.$|^[A-Z][A-Z_]{2,}$|^'?[A-Z][A-Z_]{2,}'?$")


def quoted(text: str) -> list[str]:
    """The command lines of a Markdown page: fenced code lines (backslash continuations joined) and inline spans."""
    lines = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S):
        lines += [line.strip() for line in block.replace("\\\n", " ").splitlines()]
    prose = re.sub(r"```[a-z]*\n.*?```", "", text, flags=re.S)
    lines += [" ".join(span.split()) for span in re.findall(r"`([^`]+)`", prose)]
    return lines


def commands(text: str) -> list[list[str]]:
    """The repository's scripts that the page's lines run, as argument lists [file, args...]."""
    return [words for line in quoted(text) for words in line_commands(line)]


def line_commands(line: str) -> list[list[str]]:
    """The repository's scripts that one quoted line runs."""
    found = []
    line = re.split(r"\s#\s|\s#$", line)[0]  # a trailing comment
    line = re.sub(r"<[^<>]*>", "<x>", line)  # <its flags>: one placeholder
    for part in re.split(r"&&|\|\||;|\|", line):
        try:
            words = shlex.split(part.replace("[", " ").replace("]", " "))
        except ValueError:
            continue
        while words and re.fullmatch(r"[A-Z_]+=\S*", words[0]):  # MUJOCO_GL=egl ...
            words = words[1:]
        if words and words[0] in ("python", "python3"):
            words = words[1:]
        if words and re.fullmatch(r"(\./)?[\w./-]+\.(py|sh)", words[0]) and not words[0].startswith("/"):
            if (ROOT / words[0]).suffix and words[0].split("/")[0] in {
                    p.name for p in ROOT.iterdir()} | {"benchmarks", "experiments", "tests"}:
                found.append(words)
    return found


def flags_of(words: list[str]) -> list[str]:
    return [word.split("=", 1)[0] for word in words if word.startswith("--") and len(word) > 2]


def run_main(path: Path, argv: list[str]) -> tuple[int, str]:
    """Runs a script as __main__ with these arguments in this process; (exit code, stdout + stderr)."""
    out = io.StringIO()
    saved = sys.argv
    sys.argv = [str(path), *argv]
    code = 0
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            runpy.run_path(str(path), run_name="__main__")
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 1)
    except Exception as error:  # noqa: BLE001 (a script's own failure is the finding)
        code = 1
        out.write(f"{type(error).__name__}: {error}")
    finally:
        sys.argv = saved
    return code, out.getvalue()


HELP = {}
CHECKED = []  # every command checked, for the test's count


def known_flags(path: Path, prefix: tuple[str, ...] = ()) -> set[str] | str:
    """The flags of a script's --help (a grid preset's, given as prefix), or the error text."""
    key = (path, prefix)
    if key not in HELP:
        code, text = run_main(path, [*prefix, "--help"])
        HELP[key] = set(re.findall(r"--[a-z0-9][a-z0-9-]*", text)) if code == 0 else text.strip()[-300:]
    return HELP[key]


@functools.cache
def episode_len(script: str, env_id: str) -> int:
    """The script's make_env(env_id)'s episode length; each environment is built once."""
    return importlib.import_module(script.removesuffix(".py")).make_env(env_id)[1]


def parse_algorithm(script: str, argv: list[str]) -> str | None:
    """What the script says before any work for these flags: None if they pass, else its error line."""
    module = importlib.import_module(script.removesuffix(".py"))
    saved = sys.argv
    sys.argv = [script, *argv]
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            args = module.parse_args()
            module.check_args(args, episode_len(script, args.env_id))
    except SystemExit as exit_:
        return None if not exit_.code else (err.getvalue().strip() or f"exit {exit_.code}")
    except (ValueError, OSError) as error:
        return str(error)
    finally:
        sys.argv = saved
    return None


class Parsed(BaseException):
    """Raised where tyro.cli or argparse's parse_args would return: the script stops once its command line has parsed
    (not an Exception, so that no `except Exception` of the script catches it)."""


def filled(args: list[str]) -> list[str]:
    """The command with a value for each placeholder: <x> or ... where a flag's value cannot be (after the script or
    another value) stands for more flags and is left out; any other placeholder becomes 1, which a parser takes as a
    path, a string or a number."""
    words = []
    for i, word in enumerate(args):
        if word in ("<x>", "...") and not (i and args[i - 1].startswith("--") and "=" not in args[i - 1]):
            continue
        words.append(re.sub(r"<[^>]*>|^\.\.\.$|^'?[A-Z][A-Z_]{2,}'?$", "1", word))
    return words


def parse_only(path: Path, argv: list[str]) -> str | None:
    """None if the script's own parser accepts argv, else its error; nothing after the parsing runs."""
    import argparse

    import tyro

    def stop(parse):
        def parsed(*args, **kwargs):
            parse(*args, **kwargs)
            raise Parsed
        return parsed

    saved = tyro.cli, argparse.ArgumentParser.parse_args
    tyro.cli, argparse.ArgumentParser.parse_args = stop(tyro.cli), stop(argparse.ArgumentParser.parse_args)
    try:
        code, text = run_main(path, argv)
    except Parsed:
        return None
    finally:
        tyro.cli, argparse.ArgumentParser.parse_args = saved
    summary = re.sub(r"[-─]{3,}|For full helptext.*", " ", text, flags=re.S)  # tyro's box, without its frame
    return " ".join(summary.split())[:300] or f"exit {code}"


def check(words: list[str]) -> str | None:
    """None if the command fits the code, else what is wrong."""
    CHECKED.append(words)
    path = ROOT / words[0]
    if not path.is_file():
        return f"{words[0]}: no such file"
    if path.suffix == ".sh" or path.name in NOT_HERE:
        return None
    args = words[1:]
    if not args:  # a file named in the prose
        return None
    if not re.search(r"\b(argparse|tyro)\b", path.read_text()):  # a script without a command line
        return f"{words[0]} takes no flags" if flags_of(args) else None
    placeholder = any(PLACEHOLDER.search(word) for word in args) or bool({"--resume", "--labels-from"} & set(args))
    if path.name == "edits.py":  # edits.py EDIT... [--write FILE] [-- SCRIPT FLAGS]
        cut = args.index("--") if "--" in args else len(args)
        edits = importlib.import_module("benchmarks.reference.edits").EDITS
        names = [name for i, name in enumerate(args[:cut]) if not name.startswith("-") and args[i - 1] != "--write"]
        if unknown := [name for name in names if name not in edits and not PLACEHOLDER.search(name)]:
            return f"edits.py: no edit {unknown[0]!r}"
        return check(args[cut + 1:]) if cut + 1 < len(args) else None
    prefix = ()
    if path.name == "grid.py" and args and not args[0].startswith("-") and not PLACEHOLDER.search(args[0]):
        if args[0] not in importlib.import_module("grid").PRESETS:
            return f"grid.py: no preset {args[0]!r}"
        prefix = (args[0],)
    flags = known_flags(path, prefix)
    if isinstance(flags, str):
        return f"{' '.join(words[:2])} --help fails: {flags}"
    if unknown := [flag for flag in flags_of(args) if flag not in flags]:
        return f"{words[0]}: no flag {unknown[0]}"
    if path.name == "grid.py":  # --flags='...' and --pebble-flags='...': the scripts' flags
        for i, word in enumerate(args):
            name, _, value = word.partition("=")
            if name.endswith("flags") and name.startswith("--"):
                value = value or (args[i + 1] if i + 1 < len(args) else "")
                scripts = [f"{name[2:-6]}.py"] if name != "--flags" else list(ALGORITHMS)
                known = set().union(*(known_flags(ROOT / script) for script in scripts))
                if unknown := [flag for flag in flags_of(shlex.split(value)) if flag not in known]:
                    return f"{name}: no flag {unknown[0]} in {', '.join(scripts)}"
    if "--help" in args:
        return None
    parses_alone = re.search(r"tyro\.cli\(|\.parse_args\(", path.read_text()) and path.name != "grid.py"
    resumes = {"--resume", "--labels-from"} & set(args)  # these read the run's files while parsing
    if placeholder and parses_alone and not resumes and (error := parse_only(path, filled(args))):
        return f"{words[0]} refuses its command line (placeholders filled in): {error}"
    if placeholder:
        return None
    if path.name in ALGORITHMS and path.parent == ROOT:
        error = parse_algorithm(path.name, args)
        return f"{path.name} refuses its flags: {error}" if error else None
    if path.name == "grid.py" and prefix:
        with tempfile.TemporaryDirectory() as root:
            code, text = run_main(path, [*args, "--root", root, "--dry-run"])
        return f"grid.py {args[0]} --dry-run fails: {text.strip()[-300:]}" if code else None
    return None


NUMBERS = dict(zip(("one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten"), range(1, 11)))
COUNT = re.compile(rf"\b(\d+|{'|'.join(NUMBERS)}) seeds?\b|\bseeds (\d+)-(\d+)\b", re.I)


def stated_seeds(text: str) -> list[tuple[int, str]]:
    """The seed counts a piece of a page states, in order, with their words: "N seeds" ("five seeds", "1 seed"), "seeds A-B",
    and the cells of a table's "seeds" column ("5", "1 2 3 4 5"; "5 / 3" states both). Code spans say nothing."""
    found, column = [], None
    for line in re.sub(r"`[^`]*`", " ", text).splitlines():
        found += [(int(NUMBERS.get(m[1].lower(), m[1])) if m[1] else int(m[3]) - int(m[2]) + 1, m[0])
                  for m in COUNT.finditer(line)]
        if not line.lstrip().startswith("|"):
            column = None
            continue
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if column is None:  # a table's header
            column = next((i for i, cell in enumerate(cells) if cell.lower().startswith("seeds")), -1)
        elif 0 <= column < len(cells) and re.fullmatch(r"[\d /]+", cells[column]):
            for part in cells[column].split("/"):
                numbers = part.split()
                count = int(numbers[0]) if len(numbers) == 1 else len(numbers)
                found.append((count, f"{cells[column]} in the seeds column"))
    return found


def seeds_run(words: list[str]) -> int | None:
    """How many seeds a grid preset's command runs (its --seeds, else the preset's); None for another command."""
    args = words[1:]
    if Path(words[0]).name != "grid.py" or not args or args[0] not in importlib.import_module("grid").PRESETS:
        return None
    if "--seeds" in args:
        given = args[args.index("--seeds") + 1:]
        return next((i for i, word in enumerate(given) if word.startswith("-")), len(given))
    return len(importlib.import_module("grid").PRESETS[args[0]][1].seeds)


def seed_mismatches(page: Path) -> list[str]:
    """A grid preset's command beside another seed count than it runs: the count of its comment ("# 5 seeds"), else
    the last one stated before it in its paragraph; for a code block, in the paragraph or table above the block."""
    found = []

    def compare(line: str, stated: list[tuple[int, str]]):
        for words in line_commands(" ".join(line.split())):
            if stated and (count := seeds_run(words)) is not None and count != stated[-1][0]:
                found.append(f"{page.name}: `{' '.join(words)}` runs {count} seeds, beside {stated[-1][1]!r}")

    text = page.read_text()
    for block in re.finditer(r"```[a-z]*\n(.*?)```", text, re.S):
        before = text[: block.start()].rstrip()
        above = [] if before.endswith("```") else stated_seeds(before.split("\n\n")[-1])  # not a code block's
        for line in block[1].replace("\\\n", " ").splitlines():
            command, *comment = re.split(r"\s#(?=\s|$)", line, maxsplit=1)
            compare(command, stated_seeds(" ".join(comment)) or above)
    prose = re.sub(r"```[a-z]*\n.*?```", "\n\n", text, flags=re.S)
    for paragraph in prose.split("\n\n"):
        for span in re.finditer(r"`([^`]+)`", paragraph):
            compare(span[1], stated_seeds(paragraph[: span.start()]))
    return found


def anchors(page: Path) -> set[str]:
    """GitHub's anchors of a Markdown page's headings."""
    headings = re.findall(r"^#+\s+(.*)$", re.sub(r"```.*?```", "", page.read_text(), flags=re.S), re.M)
    return {re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-") for heading in headings}


def broken_links(page: Path) -> list[str]:
    """Relative links of a page whose file, or heading, does not exist."""
    found = []
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            found.append(f"{page.name}: link ({target}): no such file")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            found.append(f"{page.name}: link ({target}): no such heading in {file.name}")
    return found


def problems(pages=PAGES) -> list[str]:
    sys.path[:0] = [str(ROOT), str(ROOT / "experiments")]
    found = []
    for page in pages:
        found += broken_links(page) + seed_mismatches(page)
        for words in commands(page.read_text()):
            if error := check(words):
                found.append(f"{page.name}: `{' '.join(words)}`: {' '.join(error.replace('─', ' ').split())}")
    return found


if __name__ == "__main__":
    pages = [Path(page).resolve() for page in sys.argv[1:]] or PAGES
    sys.argv = sys.argv[:1]
    listed = problems(pages)
    print("\n".join(listed) or "every quoted command fits the code")
    sys.exit(1 if listed else 0)
