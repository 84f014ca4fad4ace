"""Files are data only: no pickle, no eval/exec, NumPy loads with ``allow_pickle=False``.

The scan reads every Python file under ``src/`` as tokens, so words in docstrings and
comments ("never a pickle") do not count, but any use in code does.
"""

import io
import tokenize
from pathlib import Path

import pytest

from paths import REPO

SRC = REPO / "src"

#: Names whose use in code runs or deserializes arbitrary objects.
FORBIDDEN_NAMES = {"pickle", "cPickle", "dill", "cloudpickle", "marshal", "shelve", "eval", "exec", "compile"}
#: Loaders that must be called with ``allow_pickle=False``.
NUMPY_LOADS = {"load"}


def _code_tokens(path: Path):
    text = path.read_text(encoding="utf-8")
    return [
        t for t in tokenize.generate_tokens(io.StringIO(text).readline)
        if t.type not in (tokenize.COMMENT, tokenize.STRING, tokenize.NL, tokenize.NEWLINE)
    ]  # fmt: skip


def _problems(path: Path, root: Path = SRC) -> list[str]:
    found = []
    tokens = _code_tokens(path)
    for i, tok in enumerate(tokens):
        if tok.type != tokenize.NAME:
            continue
        prev = tokens[i - 1].string if i else ""
        nxt = tokens[i + 1].string if i + 1 < len(tokens) else ""
        where = f"{path.relative_to(root.parent)}:{tok.start[0]}"
        if tok.string in FORBIDDEN_NAMES and not (prev == "." and tok.string == "compile"):
            # re.compile / x.compile are method calls, not the builtin.
            found.append(f"{where}: uses {tok.string}")
        if tok.string == "allow_pickle" and nxt == "=" and tokens[i + 2].string != "False":
            found.append(f"{where}: allow_pickle={tokens[i + 2].string}")
        if tok.string in NUMPY_LOADS and prev == "." and i >= 2 and tokens[i - 2].string in ("np", "numpy"):
            depth, j, args = 0, i + 1, []
            while j < len(tokens):
                depth += tokens[j].string == "("
                depth -= tokens[j].string == ")"
                args.append(tokens[j].string)
                if depth == 0:
                    break
                j += 1
            if "".join(args).find("allow_pickle=False") < 0:
                found.append(f"{where}: np.load without allow_pickle=False")
    return found


def test_no_pickle_eval_exec_in_src():
    files = sorted(SRC.rglob("*.py"))
    assert len(files) > 10
    problems = [p for f in files for p in _problems(f)]
    assert problems == []


@pytest.mark.parametrize(
    "code,bad",
    [
        ("import pickle\n", True),
        ("x = eval('1')\n", True),
        ("exec(code)\n", True),
        ("np.load(path)\n", True),
        ("np.load(path, allow_pickle=True)\n", True),
        ("np.load(path, allow_pickle=False)\n", False),
        ("pattern = re.compile('a')\n", False),
        ('"""Never a pickle, never eval."""\n# no exec\n', False),
    ],
)
def test_the_scan_itself(tmp_path, code, bad):
    """The scan finds what it must and only that (else the test above proves nothing)."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "m.py").write_text(code)
    assert bool(_problems(src / "m.py", src)) is bad
