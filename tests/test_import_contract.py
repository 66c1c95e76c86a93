"""The layers only point down: import-linter checks pyproject.toml's contracts on cfknode as installed.

An editable install maps the top-level folders into ``cfknode`` with an import hook that
import-linter cannot walk, so the check builds a plain install of the checkout first.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_import_contracts_hold(tmp_path: Path) -> None:
    target = tmp_path / "site"
    import setuptools

    # Build with this interpreter's setuptools when it is new enough for pyproject.toml (no download).
    isolation = [] if int(setuptools.__version__.split(".")[0]) < 68 else ["--no-build-isolation"]
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", *isolation,
                    "--target", str(target), str(ROOT)], check=True, capture_output=True, text=True, timeout=600,
                   cwd=tmp_path)
    shutil.rmtree(tmp_path / "build", ignore_errors=True)
    # import-linter's own command, run by this interpreter (no console-script shim on PATH needed).
    lint = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    out = subprocess.run([sys.executable, "-c", lint, str(ROOT / "pyproject.toml")], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path, env={"PYTHONPATH": str(target), "PATH": str(Path(sys.executable).parent)})
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "0 broken" in out.stdout
