"""How big the algorithm scripts are, counted as issue 33 counts them (CleanRL's SAC: 2,153 tokens, 1,784 prose).

    python benchmarks/script_size.py [pebble.py prefppo.py ...]

tokens: Python's tokenize without COMMENT, NL, NEWLINE, INDENT, DEDENT, ENDMARKER, ENCODING. prose: the characters of
comments plus every string that stands alone as a statement (docstrings, Args' field docstrings). main loop: lines of
the for/while loop in the `if __name__ == "__main__":` block. The split puts each top-level definition (and the main
block's lines) in one part by the section comment it sits under ("# Environments", "# Networks", "# Algorithm",
"# Plumbing"; the main block is its own part).
"""

import ast
import io
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER,
          tokenize.ENCODING}
GOALS = {"pebble.py": 6500, "prefppo.py": 7200}  # issue 33's token caps
SECTIONS = ("# Environments", "# Networks", "# Algorithm", "# Plumbing")


def content_tokens(source: str) -> list[tokenize.TokenInfo]:
    return [t for t in tokenize.generate_tokens(io.StringIO(source).readline) if t.type not in LAYOUT]


def prose_characters(source: str) -> int:
    comments = sum(len(t.string) for t in tokenize.generate_tokens(io.StringIO(source).readline)
                   if t.type == tokenize.COMMENT)
    strings = sum(len(node.value.value) for node in ast.walk(ast.parse(source))
                  if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
                  and isinstance(node.value.value, str))
    return comments + strings


def main_loop_lines(source: str) -> int:
    """Lines of the longest for/while statement directly in the main block (or in a try there)."""
    for node in ast.parse(source).body:
        if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test):
            body = [inner for child in node.body for inner in ([child] + getattr(child, "body", []))]
            loops = [child for child in body if isinstance(child, (ast.For, ast.While))]
            return max((loop.end_lineno - loop.lineno + 1 for loop in loops), default=0)
    return 0


def split(source: str) -> dict[str, int]:
    """Content tokens per section: Args and presets before "# Environments", then each section, then the main."""
    lines = source.splitlines()
    section_of_line, current = {}, "Args, presets"
    for number, line in enumerate(lines, 1):
        for name in SECTIONS:
            if line.startswith(name):
                current = name[2:].split(":")[0]
        if line.startswith('if __name__ == "__main__":'):
            current = "main block"
        section_of_line[number] = current
    parts = {}
    for token in content_tokens(source):
        part = section_of_line.get(token.start[0], current)
        parts[part] = parts.get(part, 0) + 1
    return parts


def report(paths: list[str]) -> str:
    rows = ["| script | tokens | goal | prose chars | longest line | main loop lines | lines |",
            "|---|---|---|---|---|---|---|"]
    splits = []
    for path in paths:
        source = (ROOT / path).read_text()
        tokens = len(content_tokens(source))
        longest = max(map(len, source.splitlines()))
        rows.append(f"| {path} | {tokens} | {GOALS.get(path, '-')} | {prose_characters(source)} | {longest} | "
                    f"{main_loop_lines(source)} | {len(source.splitlines())} |")
        splits.append(f"{path}: " + ", ".join(f"{part} {count}" for part, count in split(source).items()))
    return "\n".join(rows + [""] + splits)


if __name__ == "__main__":
    print(report(sys.argv[1:] or [*GOALS, "rime.py", "qpa.py"]))
