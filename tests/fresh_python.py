"""Code run in a fresh Python process, for tests in any folder of ``tests/`` that check what
an import or a command loads (a module imported once stays in this process's ``sys.modules``)."""

import subprocess
import sys

#: The line between what the code printed and the names of the modules loaded.
_MARK = "--- sys.modules ---"


def run_fresh(code: str) -> tuple[str, set[str]]:
    """Run ``code`` in a new process of this interpreter: ``(what it printed, the names in
    its sys.modules afterwards)``; a failing run raises ``CalledProcessError``."""
    script = f"{code}\nimport sys\nprint({_MARK!r})\nprint('\\n'.join(sys.modules))"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    printed, _, names = out.stdout.rpartition(_MARK + "\n")
    return printed, set(names.split())
