"""The documentation cannot rot: the site builds with ``mkdocs build --strict`` (broken
links, missing API objects and warnings fail it), and the docstrings' examples run, each in
a fresh process (the pages' and the README's Python blocks: tests/test_docs_examples.py)."""

from __future__ import annotations

import ast
import html
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)


def python_blocks(page: Path) -> list[str]:
    return PYTHON_BLOCK.findall(page.read_text())


def docstring_examples() -> dict[str, str]:
    """The literal blocks (after a line ending in ``::``) of every docstring of the package,
    by ``module:object``; each is a complete example."""
    examples = {}
    for path in [*sorted((ROOT / "spacegrasp_jax").rglob("*.py")), *sorted((ROOT / "tuning").glob("*.py"))]:
        tree = ast.parse(path.read_text())
        for node in [tree, *ast.walk(tree)]:
            if not isinstance(node, (ast.Module, ast.FunctionDef, ast.ClassDef)):
                continue
            docstring = ast.get_docstring(node)
            if not docstring or "::\n" not in docstring:
                continue
            block = docstring.split("::\n", 1)[1]
            lines = []
            for line in block.splitlines()[1:] if block.startswith("\n") else block.splitlines():
                if line and not line.startswith("    "):
                    break
                lines.append(line)
            example = textwrap.dedent("\n".join(lines))
            if "import spacegrasp_jax" in example:  # a program, not a file format
                examples[f"{path.relative_to(ROOT)}:{getattr(node, 'name', 'module')}"] = example
    return examples


#: A Sphinx role that Markdown left as text: ``:func:`` before a backtick (a role the
#: renderer did not touch) or before ``<code>`` (one whose backticks became a code span).
RAW_ROLE = re.compile(r":(?:py:)?(?:func|class|data|mod|meth|attr|exc|obj|const):(?:`|<code>)")


def raw_roles(page_html: str) -> list[str]:
    """The Sphinx roles left as text on a built page, as they read there."""
    return RAW_ROLE.findall(html.unescape(page_html))


def test_the_raw_role_check_sees_a_role_in_each_form_it_renders_to():
    """The check of the built site, tested on the forms a role takes: untouched, and with its
    backticks made a code span (how mkdocstrings renders ``:func:`csv_columns```), each found;
    a cross-reference rendered as a link, and prose that merely holds a colon, not."""
    assert raw_roles("<p>A CSV file (:func:<code>csv_columns</code>), one row</p>") == [":func:<code>"]
    assert raw_roles("<p>see :py:class:`Frames`</p>") == [":py:class:`"]
    assert raw_roles("<p>:data:&lt;code&gt;STYLES&lt;/code&gt;</p>") == [":data:<code>"]
    link = '<a class="autorefs" href="#spacegrasp_jax.jobs.runfiles.csv_columns"><code>csv_columns</code></a>'
    assert raw_roles(f"<p>A CSV file ({link}), ratio 1:2, time 12:30</p>") == []


def test_the_site_builds_strictly(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "site" / "reference" / "simulation" / "index.html").exists()
    # The API reference renders: no Sphinx role left as text (cross-references are links),
    # every Attributes: section a table rather than a paragraph that starts with the word.
    for page in (tmp_path / "site").rglob("*.html"):
        text = page.read_text()
        assert not raw_roles(text), f"raw roles {raw_roles(text)} in {page}"
        assert "<p>Attributes:" not in text, f"an Attributes: section rendered as a paragraph in {page}"
    reference = (tmp_path / "site" / "reference" / "simulation" / "index.html").read_text()
    assert 'href="../dynamics/#spacegrasp_jax.core.kinematics.Frames"' in reference  # a role became a link


def test_the_pages_with_examples_are_the_ones_expected():
    # A page that gains or loses its examples is noticed (each is run below).
    with_examples = {page.name for page in PAGES if python_blocks(page)}
    assert with_examples == {
        "README.md",
        "getting-started.md",
        "python-api.md",
        "tuning.md",
        "monte-carlo.md",
        "file-formats.md",
        "flight-like-loop.md",
        "free-target.md",
        "flight-software.md",
        "gain-schedules.md",
        "your-own-arm.md",
        "your-own-law.md",
    }


def test_the_docstrings_examples_are_the_ones_expected():
    assert set(docstring_examples()) == {
        "spacegrasp_jax/__init__.py:module",
        "spacegrasp_jax/jobs/compilation.py:configure",
        "spacegrasp_jax/analysis/sweep.py:module",
    }


#: Examples that compile a whole program (the sweep's batch of rollouts): the slow tier.
SLOW_EXAMPLES = {"spacegrasp_jax/analysis/sweep.py:module"}


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(name, marks=pytest.mark.slow) if name in SLOW_EXAMPLES else name
        for name in sorted(docstring_examples())
    ],
)
def test_every_docstring_example_runs(name):
    script = docstring_examples()[name]
    assert "sg.configure()" in script  # which uses the test run's compilation cache (conftest.py)
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, f"{name}:\n{script}\n{result.stderr[-4000:]}"
