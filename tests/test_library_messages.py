"""Library messages name Python parameters; only the command line names its flags.

Every string literal in ``src/oapcal`` outside ``cli/`` (docstrings and comments aside) is
read with :mod:`ast`; one that names a command-line flag (``--word``) is a message written
for the command line inside the library.  The command line adds the flag to a library
message through ``OapcalError.param`` (and ``param`` on the detection and file results).
"""

import ast
import re

from paths import SRC

#: ``--word``, not a CSS custom property (``--ink: #222``, ``var(--ink)``) of the report's style
FLAG = re.compile(r"(?<![\w-])(?<!var\()--[a-z][a-z0-9-]*(?![\w:-])")

#: Modules whose messages still name flags, with the flags (none left).
KNOWN: dict[str, set[str]] = {}


def _docstrings(tree) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                ids.add(id(body[0].value))
    return ids


def _flags_in_messages() -> dict[str, set[str]]:
    root = SRC
    found: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel.startswith("cli/"):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        skip = _docstrings(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
                flags = set(FLAG.findall(node.value))
                if flags:
                    found.setdefault(rel, set()).update(flags)
    return found


def test_library_messages_name_no_command_line_flags():
    found = _flags_in_messages()
    new = {m: f - KNOWN.get(m, set()) for m, f in found.items()}
    assert not {m: f for m, f in new.items() if f}, "library strings that name command-line flags"
    fixed = {m: f - found.get(m, set()) for m, f in KNOWN.items()}
    assert not {m: f for m, f in fixed.items() if f}, "fixed: remove them from KNOWN"


def test_the_scan_finds_a_flag_in_a_message(tmp_path):
    # the scan reads messages, not docstrings: a negative control of both
    tree = ast.parse('"""Run oapcal fit --model paper."""\nraise ValueError("give --um-per-px")\n')
    skip = _docstrings(tree)
    texts = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and id(n) not in skip]
    assert [FLAG.findall(t) for t in texts] == [["--um-per-px"]]
    assert FLAG.findall("a -- b, x--y, --x-column") == ["--x-column"]
    assert FLAG.findall("p { --ink: #222; color: var(--ink); }") == []
