"""The docs name files that exist, and their links land on headings that exist.

Every backticked repository path in docs/*.md and README.md (`flight/estimator.py`,
`docs/results.md`, `cfknode/config/default.yaml`, ...) and every backticked module name
(`cfknode.flight.latency`) must exist in the checkout, and every
link to a docs page's heading (`docs/results.md#bench-timing` anywhere in the tree,
`(results.md#bench-timing)` or `(#bench-timing)` inside docs/) must name a heading of that page.
A moved or renamed file, or a renamed section, fails here instead of leaving a stale name behind.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = sorted(DOCS.glob("*.md")) + [ROOT / "README.md"]

# The repository's own top-level folders and files, and the flight log folder: a backticked path
# under one of them is a claim about this checkout. (README's tree of `cfknode/`, written as
# `app/`, `ui/`, ..., is relative to that folder and not checked.)
# A bench's output folder (`--out`, ./bench_out by default) is the reader's too: run in a checkout, it must not
# make the docs' mention of its files a claim about the repository.
TOP = frozenset(p.name for p in ROOT.iterdir() if not p.name.startswith(".")) - {"bench_out"} | {"flights"}

# Backticked paths that are a user's own files, not files of this repository: what the reader's
# own flights write (a fresh clone has no flights/ until the first flight).
USER_FILES = frozenset({
    "flights/",  # log.dir, where every flight's log is written
})

_TICKED = re.compile(r"`([^`\s]+)`")
_FILE_LIKE = re.compile(r"^[A-Za-z0-9_.\-/*]+\.(py|md|yaml|yml|toml|json|png|txt|cfg|sh|mcap|ckpt)$")


def _repo_paths(text: str) -> set[str]:
    """Backticked tokens that name a path in this repository (a folder of it, then a file)."""
    found = set()
    for token in _TICKED.findall(text):
        token = token.split("#", 1)[0].rstrip(":,.")
        if "/" not in token or token.startswith(("/", "sim:", "radio:")):
            continue
        if token.split("/", 1)[0] not in TOP:
            continue
        if _FILE_LIKE.match(token) or token.endswith("/"):
            found.add(token)
    return found


_LINK_TARGET = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")


def test_relative_links_land_on_files():
    missing = []
    for page in PAGES:
        for target in _LINK_TARGET.findall(page.read_text(encoding="utf-8")):
            if re.match(r"^[a-z]+:", target):
                continue
            if not (page.parent / target).exists():
                missing.append(f"{page.relative_to(ROOT)}: ({target})")
    assert not missing, "links to files that are not in the repository:\n" + "\n".join(missing)


def _exists(path: str) -> bool:
    if "*" in path:
        return any(ROOT.glob(path))
    return (ROOT / path).exists()


def test_backticked_repository_paths_exist():
    missing = []
    for page in PAGES:
        for path in sorted(_repo_paths(page.read_text(encoding="utf-8"))):
            if path not in USER_FILES and not _exists(path):
                missing.append(f"{page.relative_to(ROOT)}: `{path}`")
    assert not missing, "paths named in the docs that are not in the repository:\n" + "\n".join(missing)


def _package_dirs() -> dict[str, Path]:
    """Import path -> folder, from pyproject's package-dir (a folder's name is not always its import path)."""
    import tomllib

    with open(ROOT / "pyproject.toml", "rb") as f:
        mapping = tomllib.load(f)["tool"]["setuptools"].get("package-dir", {})
    return {name: ROOT / folder for name, folder in mapping.items()}


def _module_exists(dotted: str, dirs: dict[str, Path]) -> bool:
    """`cfknode.a.b` names a module or package of this repository (or an attribute of one)."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        base = ".".join(parts[:cut])
        if base in dirs:
            path = dirs[base].joinpath(*parts[cut:])
            if path.is_dir() or path.with_suffix(".py").exists():
                return True
            # the last part may be a function or a constant of a module
            module = dirs[base].joinpath(*parts[cut:-1])
            module = module / "__init__.py" if module.is_dir() else module.with_suffix(".py")
            return module.exists() and re.search(
                rf"^(def |class )?{parts[-1]}\b", module.read_text(encoding="utf-8"), re.M) is not None
    return False


def test_backticked_module_names_exist():
    dirs = _package_dirs()
    missing = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for name in sorted(set(re.findall(r"`(cfknode(?:\.[a-z_][a-z0-9_]*)+)`", text))):
            if not _module_exists(name, dirs):
                missing.append(f"{page.relative_to(ROOT)}: `{name}`")
    assert not missing, "modules named in the docs that are not in the repository:\n" + "\n".join(missing)


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*]", "", heading.strip()).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    anchors = set()
    in_code = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            in_code = not in_code
            continue
        m = re.match(r"^#{1,6}\s+(.*)$", line)
        if m and not in_code:
            slug = _slug(m.group(1))
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


_TREE_LINK = re.compile(r"docs/([\w\-]+\.md)#([\w\-]+)")
_DOCS_LINK = re.compile(r"\]\(([\w\-]+\.md)?#([\w\-]+)\)")


_NOT_SOURCE = {"build", "dist", "flights", "bench_out"}
_TEXT = (".md", ".py", ".yaml", ".toml")


def _tree_files():
    """The repository's text files (hidden folders such as a virtual environment, logs, builds left out)."""
    for top in sorted(ROOT.iterdir()):
        if top.name.startswith(".") or top.name in _NOT_SOURCE or top.name.endswith(".egg-info"):
            continue
        if top.is_file():
            if top.suffix in _TEXT:
                yield top
            continue
        for path in top.rglob("*"):
            if path.suffix in _TEXT and path.is_file():
                yield path


def test_links_to_docs_headings_resolve():
    anchors = {page.name: _anchors(page) for page in DOCS.glob("*.md")}
    broken = []
    for path in _tree_files():
        if path == Path(__file__).resolve():
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        links = [(page, anchor) for page, anchor in _TREE_LINK.findall(text)]
        if path.parent == DOCS:
            links += [(page or path.name, anchor) for page, anchor in _DOCS_LINK.findall(text)]
        for page, anchor in links:
            if anchor not in anchors.get(page, set()):
                broken.append(f"{path.relative_to(ROOT)}: {page}#{anchor}")
    assert not broken, "links to headings that do not exist:\n" + "\n".join(sorted(set(broken)))


def test_the_checks_see_what_they_check():
    # the path pattern and the slugs on known cases, so an empty scan cannot pass unnoticed
    assert _repo_paths("see `flight/estimator.py` and `docs/results.md#x`, not `sim://0`") == {
        "flight/estimator.py", "docs/results.md"}
    assert _repo_paths("`flights/*-heavy.mcap`") == {"flights/*-heavy.mcap"}
    assert _slug("Latency compensation (`estimator.command_delay`)") == (
        "latency-compensation-estimatorcommand_delay")
    assert _slug("The estimator's input") == "the-estimators-input"
    assert "bench-timing" in _anchors(DOCS / "results.md")
    dirs = _package_dirs()
    assert _module_exists("cfknode.flight.estimator", dirs)
    assert not _module_exists("cfknode.flight.no_such_module", dirs)
    assert _module_exists("cfknode.app.bench.thrust_sag.lag_sag", dirs)
    assert not _module_exists("cfknode.app.bench.thrust_sag.no_such_function", dirs)
