"""Compile a CasADi Function to a shared library once per machine and load it back.

The generated C source is hashed (together with the compiler command and CasADi
version), so a cached library is reused until the problem, CasADi or the compiler
changes.  Writes are atomic: a library is compiled into a private temporary file in
the cache folder and then renamed over its final name, so two processes that
compile at the same time both end up loading a complete file.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca

# -O2 as the brief asks; -march stays generic so a cache folder shared between
# machines (NFS home) never holds a library the CPU can't run. Partial-redundancy elimination and
# global CSE took 2/3 of gcc's time on the generated straight-line step (14.6 s -> 5.4 s for 20 nodes)
# and gained nothing measurable in the solve; the numbers are the same to the bit (docs/results.md).
CFLAGS = ("-O2", "-fno-tree-pre", "-fno-gcse", "-shared", "-fPIC")


@dataclass(frozen=True)
class CompiledFunction:
    """A generated-code Function and where it came from."""

    function: Any  # casadi.Function (external)
    library: Path
    compiled_now: bool  # False when the library came from the cache
    compile_seconds: float


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/cfknode``, or ``~/.cache/cfknode``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "cfknode"


def casadi_link_flags(plugins: tuple[str, ...]) -> tuple[list[str], list[str]]:
    """Include and link flags for generated code that calls a solver library shipped with CasADi.

    qrqp needs none (its runtime is written into the source); osqp needs the
    headers and ``libosqp`` from the CasADi wheel.
    """
    root = Path(ca.__file__).parent
    includes: list[str] = []
    libs: list[str] = []
    for name in plugins:
        if name == "osqp":
            includes += [f"-I{root / 'include' / 'osqp'}", f"-I{root / 'include'}"]
            libs += [f"-L{root}", f"-Wl,-rpath,{root}", "-losqp"]
    return includes, libs


def compile_cached(
    function: Any,
    cache_dir: Path | None = None,
    includes: list[str] | None = None,
    libs: list[str] | None = None,
    compiler: str = "gcc",
) -> CompiledFunction:
    """Generate C for ``function``, compile it (or reuse the cached library) and load it.

    Raises ``RuntimeError`` when code generation or compilation fails; the caller
    decides whether to fall back to the CasADi virtual machine.
    """
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    cc = shutil.which(compiler)
    if cc is None:
        raise RuntimeError(f"C compiler {compiler!r} not found")
    includes = list(includes or [])
    libs = list(libs or [])
    name = function.name()
    source = _generate_source(function, cache)
    command = [cc, *CFLAGS, *includes]
    key = hashlib.sha256(
        "\0".join([source, " ".join(command), " ".join(libs), ca.__version__, _compiler_version(cc)]).encode()
    ).hexdigest()[:20]
    library = cache / f"{name}_{key}.so"
    t0 = time.perf_counter()
    compiled_now = False
    if not library.is_file():
        _compile_atomic(source, command, libs, library, cache)
        compiled_now = True
    seconds = time.perf_counter() - t0
    return CompiledFunction(ca.external(name, str(library)), library, compiled_now, seconds)


def _generate_source(function: Any, workdir: Path) -> str:
    """The generated C source as text (CasADi writes it to a file; read it back)."""
    with tempfile.TemporaryDirectory(dir=workdir, prefix=".gen-") as tmp:
        cg = ca.CodeGenerator(f"{function.name()}.c", {"with_header": False, "verbose": False})
        cg.add(function)
        path = cg.generate(tmp + os.sep)
        return Path(path).read_text()


def _compile_atomic(source: str, command: list[str], libs: list[str], library: Path, cache: Path) -> None:
    with tempfile.TemporaryDirectory(dir=cache, prefix=".build-") as tmp:
        src = Path(tmp) / f"{library.stem}.c"
        src.write_text(source)
        out = Path(tmp) / library.name
        proc = subprocess.run(
            [*command, str(src), "-o", str(out), *libs, "-lm"], capture_output=True, text=True, check=False
        )
        if proc.returncode != 0 or not out.is_file():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-5:]
            raise RuntimeError(f"compiling {src.name} failed: " + " | ".join(tail))
        # Same filesystem (tmp lives inside the cache), so the rename is atomic: a
        # concurrent process sees either no library or a complete one.
        os.replace(out, library)


def _compiler_version(cc: str) -> str:
    try:
        return subprocess.run([cc, "--version"], capture_output=True, text=True, check=False).stdout.splitlines()[0]
    except (OSError, IndexError):
        return "unknown"
