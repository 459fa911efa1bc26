"""The book as a reader sees it.

Builds the book in fast mode (``FLNOTES_FAST=1``) into ``_build/test_html`` with the
same strictness as ``make book`` (warnings are errors, every notebook executed),
then checks the HTML. When nbmake executes every notebook of ``_toc.yml`` in the same
pytest session (``make test``), the book is built from those executed notebooks (a
copy of the sources with ``execute_notebooks: off``, see ``tests/conftest.py``) instead
of executing them a second time; then the table of ``book/exec_times.md`` lists no
execution (it does in ``make book``). Alone (``pytest tests/test_rendered.py``), the
build executes the notebooks itself. The checks:

* static checks, always: MathJax is loaded from the book's own ``_static`` (no CDN;
  other external scripts, such as the ipywidgets manager, only raise a warning), every ``<img>`` resolves to a file, every
  internal link resolves to a file and, with a fragment, to an anchor in it;
* in a browser, when Debian's ``chromium`` is there (installed on the fly with
  apt-get when running as root): the intro and every chapter page are opened in
  headless Chromium; after its scripts ran, the math must be typeset by MathJax
  (``mjx-container`` present, no raw ``$$``, ``\\(`` or ``\\[`` left in the text).
  Screenshots are written to ``_build/screenshots/``;
* the explorers: every chapter that calls one embeds a kernel-free player (frames as
  data URIs); in Chromium, with every other host unreachable, moving its sliders swaps
  the picture.

Set ``FLNOTES_RENDERED_HTML=<folder with index.html>`` to check an existing build
(e.g. ``_build/html`` after ``make book``) instead of building again.
"""
from __future__ import annotations

import functools
import json
import http.server
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
BUILD_OUT = ROOT / "_build" / "test_html"
SCREENSHOTS = ROOT / "_build" / "screenshots"
BUILD_TIMEOUT = int(os.environ.get("FLNOTES_RENDER_TIMEOUT", "3600"))


# ----------------------------------------------------------------------------------
# the build
def _jupyter_book_cmd() -> list[str]:
    exe = Path(sys.executable).parent / "jupyter-book"
    if exe.exists():
        return [str(exe)]
    return [sys.executable, "-c", "from jupyter_book.cli.main import main; main()"]


_BUILD_FAILURE: list[str] = []


def _problems(log_text: str, limit: int = 40) -> str:
    """The lines of a build log that say what went wrong (warnings, errors, tracebacks' ends)."""
    keep = [
        re.sub(r"\x1b\[[0-9;]*m", "", line)
        for line in log_text.splitlines()
        if re.search(r"WARNING|ERROR|Error|Exception|Traceback", line) and "IPKernelApp" not in line
        and "ParserConfig(" not in line
    ]
    more = f"\n  ... {len(keep) - limit} more" if len(keep) > limit else ""
    return "\n  ".join(keep[:limit]) + more


#: seconds html_dir waits for nbmake to execute the book's notebooks (they are handed out before it)
WAIT_TIMEOUT = int(os.environ.get("FLNOTES_RENDER_WAIT", "3600"))
#: what the staging tree of a build from executed notebooks holds, besides the notebooks
SOURCES = ("_config.yml", "_toc.yml", "book", "_ext")


def _toc_notebooks() -> list[Path]:
    """The notebooks among the pages of ``_toc.yml`` that the book executes.

    Not those whose metadata say ``mystnb: execution_mode: off`` (the students' versions of
    the assignments): the book shows them as committed, without outputs.
    """
    out = []
    for p in _toc_pages():
        path = ROOT / f"{p}.ipynb"
        if path.is_file():
            meta = json.loads(path.read_text(encoding="utf-8")).get("metadata", {})
            if (meta.get("mystnb") or {}).get("execution_mode") != "off":
                out.append(path)
    return out


def _wait_for_notebooks(run_dir: Path, staged_path, notebooks: list[Path]) -> dict[Path, Path]:
    """The executed copy of each notebook, once nbmake has written it; fails if one failed or never came."""
    deadline = time.monotonic() + WAIT_TIMEOUT
    staged = {nb: staged_path(run_dir, nb) for nb in notebooks}
    while True:
        failed = [nb for nb, path in staged.items() if path.with_suffix(".failed").exists()]
        if failed:
            why = "\n  ".join(
                f"{nb.relative_to(ROOT)}: {staged[nb].with_suffix('.failed').read_text()}" for nb in failed
            )
            pytest.fail(f"the book is not built: nbmake failed on\n  {why}\n(see those notebooks' own tests)",
                        pytrace=False)
        missing = [nb for nb, path in staged.items() if not path.is_file()]
        if not missing:
            return staged
        if time.monotonic() > deadline:
            pytest.fail(
                f"waited {WAIT_TIMEOUT} s (FLNOTES_RENDER_WAIT) for nbmake to execute "
                f"{', '.join(str(nb.relative_to(ROOT)) for nb in missing)} in this session; they never "
                f"finished. tests/conftest.py must hand the notebooks out before test_rendered.py.",
                pytrace=False,
            )
        time.sleep(1.0)


def _stage_executed_book(run_dir: Path, staged: dict[Path, Path]) -> Path:
    """A copy of the book's sources with the executed notebooks and ``execute_notebooks: off``."""
    src = run_dir / "book_src"
    if src.exists():
        shutil.rmtree(src)
    src.mkdir(parents=True)
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns(".ipynb_checkpoints", "__pycache__"))
        else:
            shutil.copy2(ROOT / name, src / name)
    config = yaml.safe_load((ROOT / "_config.yml").read_text())
    assert config["execute"]["execute_notebooks"] == "force", "_config.yml: expected execute_notebooks: force"
    config["execute"]["execute_notebooks"] = "off"  # the notebooks below carry nbmake's outputs
    (src / "_config.yml").write_text(yaml.safe_dump(config, sort_keys=False))
    for nb, executed in staged.items():
        shutil.copy2(executed, src / nb.relative_to(ROOT))
    return src


@pytest.fixture(scope="module")
def html_dir(executed_notebooks) -> Path:
    given = os.environ.get("FLNOTES_RENDERED_HTML")
    if given:
        path = Path(given).resolve()
        assert (path / "index.html").is_file(), f"FLNOTES_RENDERED_HTML={given} holds no index.html"
        return path
    if _BUILD_FAILURE:  # reported in full once, by the first test that asked for the build
        pytest.fail(f"the fast build failed (see the first error of this module; log in {_BUILD_FAILURE[0]})", pytrace=False)
    env = dict(os.environ, FLNOTES_FAST="1", PYTHONDONTWRITEBYTECODE="1")
    env.pop("MPLBACKEND", None)  # let the kernels use the inline backend, so figures are rendered
    source = ROOT
    notebooks = _toc_notebooks()
    if executed_notebooks is not None and set(notebooks) <= executed_notebooks[2]:
        # nbmake executes every notebook of the book in this session, before this module: build from its outputs
        run_dir, staged_path, _ = executed_notebooks
        source = _stage_executed_book(run_dir, _wait_for_notebooks(run_dir, staged_path, notebooks))
    if BUILD_OUT.exists():
        shutil.rmtree(BUILD_OUT)
    cmd = _jupyter_book_cmd() + ["build", str(source), "--path-output", str(BUILD_OUT), "--all", "-W", "-n", "--keep-going"]
    proc = subprocess.run(cmd, cwd=source, env=env, capture_output=True, text=True, timeout=BUILD_TIMEOUT)
    log = BUILD_OUT / "build.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text(f"built from {'the notebooks nbmake executed' if source != ROOT else 'the sources'}\n"
                   + proc.stdout + "\n" + proc.stderr)
    if proc.returncode != 0:
        _BUILD_FAILURE.append(str(log))
        pytest.fail(
            f"the book does not build in fast mode with warnings as errors (exit {proc.returncode}).\n"
            f"What went wrong:\n  {_problems(proc.stdout + proc.stderr)}\nFull log: {log}",
            pytrace=False,
        )
    path = BUILD_OUT / "_build" / "html"
    assert (path / "index.html").is_file()
    return path


def _toc_pages() -> list[str]:
    toc = yaml.safe_load((ROOT / "_toc.yml").read_text())
    pages = [toc["root"]]

    def walk(entries):
        for e in entries or []:
            if "file" in e:
                pages.append(e["file"])
            walk(e.get("sections"))

    for part in toc.get("parts", []):
        walk(part.get("chapters"))
    walk(toc.get("chapters"))
    return pages


PAGES = _toc_pages()
CHAPTERS = [p for p in PAGES if p == "book/intro" or re.match(r"book/\d\d_", p)]


# ----------------------------------------------------------------------------------
# HTML parsing
class _Collector(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.ids: set[str] = set()
        self.links: list[str] = []
        self.imgs: list[str] = []
        self.scripts: list[str] = []
        self.stylesheets: list[str] = []
        self.text: list[str] = []
        self._skip = 0
        self._skip_tags = ("script", "style", "pre", "code", "textarea", "mjx-assistive-mml", "mjx-container")

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        for key in ("id", "name"):
            if a.get(key):
                self.ids.add(a[key])
        if tag == "a" and a.get("href") is not None:
            self.links.append(a["href"])
        elif tag == "img" and a.get("src") is not None:
            self.imgs.append(a["src"])
        elif tag == "script" and a.get("src"):
            self.scripts.append(a["src"])
        elif tag == "link" and "stylesheet" in (a.get("rel") or "") and a.get("href"):
            self.stylesheets.append(a["href"])
        if tag in self._skip_tags:
            self._skip += 1

    def handle_endtag(self, tag):
        if tag in self._skip_tags and self._skip:
            self._skip -= 1

    def handle_data(self, data):
        if not self._skip:
            self.text.append(data)


@functools.lru_cache(maxsize=None)
def _parse(path: Path) -> _Collector:
    c = _Collector()
    c.feed(path.read_text(encoding="utf-8", errors="replace"))
    return c


def _pages(html_dir: Path) -> list[Path]:
    return sorted(p for p in html_dir.rglob("*.html") if "_static" not in p.parts and "_sources" not in p.parts)


def _is_external(url: str) -> bool:
    return bool(urlsplit(url).scheme) or url.startswith("//")


# ----------------------------------------------------------------------------------
# static checks (no browser needed)
def test_every_toc_page_is_built(html_dir):
    missing = [p for p in PAGES if not (html_dir / f"{p}.html").is_file()]
    assert not missing, f"pages of _toc.yml missing from the HTML: {missing}"


def test_mathjax_is_local(html_dir):
    mj = html_dir / "_static" / "mathjax" / "tex-chtml.js"
    assert mj.is_file(), "the offline MathJax (sphinx-mathjax-offline) was not copied to _static/mathjax"
    with_math = 0
    others: set[str] = set()
    for page in _pages(html_dir):
        c = _parse(page)
        external = [s for s in c.scripts + c.stylesheets if _is_external(s)]
        ext_mj = [s for s in external if "mathjax" in s.lower()]
        assert not ext_mj, f"{page.relative_to(html_dir)} loads MathJax from the network: {ext_mj}"
        others.update(external)
        mj_scripts = [s for s in c.scripts if "mathjax" in s.lower()]
        for s in mj_scripts:
            target = (page.parent / unquote(urlsplit(s).path)).resolve()
            assert target.is_file(), f"{page.relative_to(html_dir)}: MathJax script {s} does not exist"
            assert target == mj.resolve(), f"{page.relative_to(html_dir)}: unexpected MathJax {s}"
        with_math += bool(mj_scripts)
    intro = _parse(html_dir / "book" / "intro.html")
    assert any("mathjax" in s for s in intro.scripts), "the intro has math but loads no MathJax"
    assert with_math >= 1
    if others:
        # not fatal: e.g. myst-nb adds require.js and the ipywidgets embed manager from
        # CDNs to pages with widget outputs; those widgets do not show offline
        warnings.warn("external scripts/stylesheets (not available offline): " + ", ".join(sorted(others)))


def test_images_exist(html_dir):
    problems = []
    for page in _pages(html_dir):
        for src in _parse(page).imgs:
            if src.startswith("data:"):
                continue
            if _is_external(src):
                problems.append(f"{page.relative_to(html_dir)}: external image {src} (not shown offline)")
                continue
            target = page.parent / unquote(urlsplit(src).path)
            if not target.is_file():
                problems.append(f"{page.relative_to(html_dir)}: missing image {src}")
    assert not problems, "\n".join(problems)


def test_internal_links_resolve(html_dir):
    problems = []
    for page in _pages(html_dir):
        for href in _parse(page).links:
            if not href or href == "#" or _is_external(href) or href.startswith(("mailto:", "javascript:")):
                continue
            parts = urlsplit(href)
            target = page if not parts.path else (page.parent / unquote(parts.path))
            if target.is_dir():
                target = target / "index.html"
            if not target.exists():
                problems.append(f"{page.relative_to(html_dir)}: link to missing {href}")
                continue
            frag = unquote(parts.fragment)
            if frag and target.suffix == ".html" and frag not in _parse(target.resolve()).ids:
                problems.append(f"{page.relative_to(html_dir)}: link {href}: no anchor #{frag}")
    assert not problems, "\n".join(problems[:50]) + (f"\n... {len(problems)} in all" if len(problems) > 50 else "")


def test_no_raw_tex_in_static_text(html_dir):
    # Sphinx turns $...$ into math nodes; a leftover $$ means a formula was not parsed
    problems = []
    for page in _pages(html_dir):
        text = "".join(_parse(page).text)
        if "$$" in text:
            problems.append(f"{page.relative_to(html_dir)}: raw $$ in the page text")
    assert not problems, "\n".join(problems)


def test_titles_have_no_math(html_dir):
    # a heading's TeX ends up in <title> and in the navigation, where MathJax does not typeset it
    problems = []
    for page in _pages(html_dir):
        m = re.search(r"<title>(.*?)</title>", page.read_text(encoding="utf-8"), re.S)
        if m and re.search(r"\\\(|\\\[|\$", m.group(1)):
            problems.append(f"{page.relative_to(html_dir)}: TeX in the page title {m.group(1)!r}; "
                            "write the heading in plain text (Unicode symbols, *italics*)")
    assert not problems, "\n".join(problems)


# ----------------------------------------------------------------------------------
# in a browser
def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser"):
        if shutil.which(name):
            return shutil.which(name)
    return None


@pytest.fixture(scope="module")
def chromium() -> str:
    exe = _chromium()
    if exe is None and hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
        try:
            subprocess.run(["apt-get", "update", "-qq"], env=env, capture_output=True, timeout=600)
            subprocess.run(["apt-get", "install", "-y", "-qq", "chromium", "chromium-driver"],
                           env=env, capture_output=True, timeout=1200)
        except (OSError, subprocess.SubprocessError):
            pass
        exe = _chromium()
    if exe is None:
        pytest.skip("Debian's chromium is not installed and could not be installed "
                    "(apt-get install chromium chromium-driver); browser checks skipped, static checks still ran")
    return exe


@pytest.fixture(scope="module")
def server(html_dir):
    handler = functools.partial(_QuietHandler, directory=str(html_dir))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # keep the test output readable
        pass


def _chrome(exe: str, profile: str, *args: str, timeout: int = 120) -> subprocess.CompletedProcess:
    flags = [
        "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--disable-dev-shm-usage", "--hide-scrollbars", f"--user-data-dir={profile}",
        "--virtual-time-budget=10000",
    ]
    return subprocess.run([exe, *flags, *args], capture_output=True, text=True, timeout=timeout)


#: TeX commands of the book's math (Greek letters, operators, relations, fonts, environments): one of them in the
#: page's visible text means TeX that was not converted. A list, not any backslash word, so that a Windows path or a
#: regular expression in prose is no alarm.
_TEX_COMMANDS = (
    "alpha beta gamma delta epsilon varepsilon zeta eta theta vartheta iota kappa lambda mu nu xi pi rho sigma tau "
    "upsilon phi varphi chi psi omega Gamma Delta Theta Lambda Xi Pi Sigma Upsilon Phi Psi Omega "
    "frac dfrac tfrac sqrt sum prod int oint lim sup inf max min arg log exp sin cos tan "
    "le leq ge geq ne neq approx sim equiv in notin subset subseteq supset cup cap setminus emptyset infty partial "
    "nabla cdot cdots ldots dots times top mid forall exists to mapsto rightarrow leftarrow Rightarrow iff "
    "mathbf mathcal mathrm mathbb mathit boldsymbol operatorname text textrm hat bar tilde dot ddot vec "
    "underline overline underbrace overbrace left right big Big quad qquad begin end label ref eqref"
).split()
#: Unconverted TeX in the page's visible text (which excludes code, scripts and MathJax's own output): inline
#: ``$...$`` holding one of the commands, or one of the commands by itself (also followed by ``_``, ``^``, a digit
#: or a brace, as in ``\Phi_{NN}`` or ``\frac12``).
_TEX_IN_TEXT = re.compile(r"\$[^$\n]*\\(?:%s)(?![A-Za-z])[^$\n]*\$|\\(?:%s)(?![A-Za-z])"
                          % ("|".join(_TEX_COMMANDS), "|".join(_TEX_COMMANDS)))


def _colours(png: Path) -> int:
    """Distinct colours in a screenshot (a page that drew nothing has one)."""
    import matplotlib.image as mpimg

    pixels = (mpimg.imread(png)[..., :3] * 255).astype(np.uint8).reshape(-1, 3)
    return len(np.unique(pixels, axis=0))


@pytest.mark.parametrize("page", CHAPTERS)
def test_page_renders_in_chromium(page, chromium, server, html_dir):
    url = f"{server}/{page}.html"
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    shot = SCREENSHOTS / (page.replace("/", "__") + ".png")
    shot.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="flnotes-chrome-") as profile:
        # one browser run: the DOM after the page's scripts ran, and a screenshot of the same rendering
        proc = _chrome(chromium, profile, "--window-size=1280,1800", f"--screenshot={shot}", "--dump-dom", url)
        dom = proc.stdout
        assert "<html" in dom.lower(), f"Chromium returned no DOM for {url}: {proc.stderr[-2000:]}"
        has_math = 'class="math' in (html_dir / f"{page}.html").read_text(encoding="utf-8")
        if has_math:
            assert "mjx-container" in dom, f"{page}: the math was not typeset by MathJax"
        c = _Collector()
        c.feed(dom)
        text = "".join(c.text)
        raw = re.findall(r"\$\$|\\\(|\\\[", text) + _TEX_IN_TEXT.findall(text)
        assert not raw, f"{page}: raw TeX left in the rendered text: {raw[:5]}"
        assert "<mjx-merror" not in dom, f"{page}: MathJax reported a TeX error"
        assert 'mathcolor="red"' not in dom, f"{page}: MathJax drew a macro it does not know (in red)"
        assert shot.is_file() and shot.stat().st_size > 10_000, f"{page}: no screenshot written"
        assert _colours(shot) >= 16, f"{page}: the screenshot is (nearly) one colour: nothing was drawn"


# ----------------------------------------------------------------------------------
# the explorers: precomputed frames behind sliders that run in the page
_PLAYER = re.compile(r'<div class="fl-static-explorer" id="([^"]+)".*?<img class="fl-frame" data-frame="([^"]+)"'
                     r'.*?src="([^"]+)".*?<script>(.*?)</script>', re.S)


def _explorer_pages() -> list[str]:
    """Chapters whose notebook calls an explorer."""
    return [p for p in CHAPTERS if (ROOT / f"{p}.ipynb").is_file()
            and re.search(r"\bexplore_\w+\(", (ROOT / f"{p}.ipynb").read_text(encoding="utf-8"))]


def _players(html: str) -> list[dict]:
    found = []
    for pid, key, src, script in _PLAYER.findall(html):
        frames = json.loads(re.search(r"var frames=(\{.*?\});var values=", script, re.S).group(1))
        block = html[html.index(f'id="{pid}"'):html.index("<script>", html.index(f'id="{pid}"'))]
        found.append(dict(id=pid, key=key, src=src, frames=frames, max=[int(m) for m in re.findall(r'max="(\d+)"', block)]))
    return found


EXPLORER_PAGES = _explorer_pages()


def test_explorers_have_kernel_free_frames(html_dir):
    assert EXPLORER_PAGES, "no chapter calls an explorer: the check below would test nothing"
    for page in EXPLORER_PAGES:
        html = (html_dir / f"{page}.html").read_text(encoding="utf-8")
        players = _players(html)
        assert players, f"{page}: an explorer is called but no kernel-free player is in the page"
        for p in players:
            assert len(p["frames"]) >= 2 and len(set(p["frames"].values())) >= 2, f"{page}: {p['id']} has a single picture"
            assert all(v.startswith("data:image/png;base64,") for v in p["frames"].values()), \
                f"{page}: {p['id']} frames must be embedded (data URIs), not fetched"
            assert p["src"] == p["frames"][p["key"]], f"{page}: {p['id']} shows a frame that is not its first one"


@pytest.mark.parametrize("page", EXPLORER_PAGES)
def test_explorer_slider_moves_offline(page, chromium, server, html_dir):
    """Moving a slider (through the handler a reader triggers) swaps the picture, with every other host unreachable."""
    players = _players((html_dir / f"{page}.html").read_text(encoding="utf-8"))
    assert players, f"{page}: no kernel-free player"
    offline = "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"
    with tempfile.TemporaryDirectory(prefix="flnotes-chrome-") as profile:
        for p in players:
            target = ",".join(str(m) if int(k) != m else "0" for k, m in zip(p["key"].split(","), p["max"]))
            assert target != p["key"]
            dom = _chrome(chromium, profile, offline, "--dump-dom", f"{server}/{page}.html#{p['id']}={target}").stdout
            m = re.search(rf'id="{re.escape(p["id"])}".*?<img[^>]*class="fl-frame"[^>]*>', dom, re.S)
            assert m, f"{page}: player {p['id']} missing from the rendered page"
            img = m.group(0)[m.group(0).rindex("<img"):]
            key = re.search(r'data-frame="([^"]+)"', img).group(1)
            src = re.search(r'src="([^"]+)"', img).group(1)
            assert key == target, f"{page}: moving {p['id']} to {target} left the picture at {key}"
            assert src == p["frames"][target] != p["src"], f"{page}: {p['id']} did not swap its picture"
