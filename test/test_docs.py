"""The README and docs/: a short README that links every page, no broken relative link, and
the result tables in docs/results.md only (each linked from the page that explains it).

Anchors follow GitHub's rules: a heading's text (markup and HTML dropped), lower case,
every character but letters, digits, ``_``, ``-`` and spaces removed, spaces turned into
``-``; a repeated anchor gets ``-1``, ``-2``, ... Headings and links inside fenced code
blocks and HTML comments do not count. Runs in well under a second.
"""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'
DOCS = ROOT / 'docs'
PAGES = sorted(DOCS.glob('*.md'))
MAX_README_LINES = 250

_FENCE = re.compile(r'^ {0,3}(```|~~~)')
_COMMENT = re.compile(r'<!--.*?-->', re.DOTALL)
_CODE_SPAN = re.compile(r'`[^`]*`')
_LINK = re.compile(r'!?\[([^\]]*)\]\(\s*<?([^)\s>]*)>?(?:\s+"[^"]*")?\s*\)')
_HEADING = re.compile(r'^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$')
_DELIMITER = re.compile(r'^\|(\s*:?-{3,}:?\s*\|)+$')


def _prose(text: str) -> str:
    """``text`` without fenced code blocks and HTML comments (blank lines in their place)."""
    lines, fenced = [], False
    for line in _COMMENT.sub(lambda m: '\n' * m.group().count('\n'), text).split('\n'):
        if _FENCE.match(line):
            fenced = not fenced
            lines.append('')
        else:
            lines.append('' if fenced else line)
    return '\n'.join(lines)


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading's text (without its numeric suffix for repeats)."""
    text = re.sub(r'!?\[([^\]]*)\]\([^)]*\)', r'\1', heading)
    text = re.sub(r'<[^>]+>', '', text).replace('`', '')
    text = re.sub(r'[^\w\- ]', '', text.strip().lower())
    return text.replace(' ', '-')


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a Markdown file, repeats numbered as GitHub numbers them."""
    seen: dict[str, int] = {}
    found = set()
    for line in _prose(path.read_text()).split('\n'):
        match = _HEADING.match(line)
        if not match:
            continue
        anchor = github_anchor(match.group(2))
        count = seen.get(anchor, 0)
        seen[anchor] = count + 1
        found.add(anchor if count == 0 else f'{anchor}-{count}')
    return found


def links(path: Path) -> list[str]:
    """The link and image targets of a Markdown file (outside code)."""
    text = _CODE_SPAN.sub('code', _prose(path.read_text()))
    return [m.group(2) for m in _LINK.finditer(text)]


def _relative(target: str) -> bool:
    return bool(target) and not re.match(r'^[a-z][a-z0-9+.-]*:', target, re.IGNORECASE)


def test_github_anchor_rules():
    assert github_anchor("Results under the paper's protocol (simulated scenes; real pair below)") == \
        'results-under-the-papers-protocol-simulated-scenes-real-pair-below'
    assert github_anchor('ROS 2 node: `facade_mapper`') == 'ros-2-node-facade_mapper'
    assert github_anchor('The façade model: build and query') == 'the-façade-model-build-and-query'
    assert github_anchor('Real scans (`real_check.py`)') == 'real-scans-real_checkpy'
    assert github_anchor('Nothing lost, nothing stuck') == 'nothing-lost-nothing-stuck'


def test_repeated_headings_and_code_blocks(tmp_path):
    page = tmp_path / 'p.md'
    page.write_text('# A\n\n```sh\n# not a heading\n[x](missing.md)\n```\n\n## A\n<!-- [y](gone.md) -->\n'
                    '[ok](#a-1) `[z](code.md)`\n')
    assert anchors(page) == {'a', 'a-1'}
    assert links(page) == ['#a-1']


def test_readme_is_short():
    lines = README.read_text().count('\n')
    assert lines <= MAX_README_LINES, f'README.md has {lines} lines; at most {MAX_README_LINES}: move text to docs/'


def test_readme_links_every_page():
    assert PAGES, 'no docs/*.md'
    linked = {(README.parent / t.split('#')[0]).resolve() for t in links(README) if _relative(t)}
    missing = [p.name for p in PAGES if p.resolve() not in linked]
    assert not missing, f'docs pages not linked from README.md: {missing}'


def test_index_links_every_page():
    index = DOCS / 'index.md'
    linked = {(DOCS / t.split('#')[0]).resolve() for t in links(index) if _relative(t)}
    missing = [p.name for p in PAGES if p != index and p.resolve() not in linked]
    assert not missing, f'docs pages not linked from docs/index.md: {missing}'


@pytest.mark.parametrize('path', [README, *PAGES], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(path):
    broken = []
    for target in links(path):
        if not _relative(target):
            continue
        file_part, _, anchor = target.partition('#')
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            broken.append(f'{target}: no such file')
        elif anchor and dest.suffix == '.md' and anchor not in anchors(dest):
            broken.append(f'{target}: no heading with anchor #{anchor} in {dest.name}')
    assert not broken, f'{path.name}: ' + '; '.join(broken)


def table_rows(path: Path) -> list[str]:
    """The data rows of a Markdown file's tables (outside code and comments), stripped: the
    rows after each table's header and delimiter row."""
    rows, previous = [], ''
    in_table = False
    for line in _prose(path.read_text()).split('\n'):
        stripped = line.strip()
        if not stripped.startswith('|'):
            in_table = False
        elif in_table:
            rows.append(stripped)
        elif _DELIMITER.match(stripped) and previous.startswith('|'):
            in_table = True
        previous = stripped
    return rows


def test_table_rows(tmp_path):
    page = tmp_path / 'p.md'
    page.write_text('| a | b |\n|---|---:|\n| 1 | 2 |\n|  | 3 |\n\ntext | x\n\n```\n| a |\n|---|\n| 9 |\n```\n'
                    '  | c |\n  | --- |\n  | 4 |\n')
    assert table_rows(page) == ['| 1 | 2 |', '|  | 3 |', '| 4 |']


def test_results_tables_live_in_results_only():
    """docs/results.md is the one home of the result tables: no row of its tables stands in
    another page (a copy would go stale); the pages explain the figures and link there."""
    rows = set(table_rows(DOCS / 'results.md'))
    assert rows
    copied = [(p.name, row) for p in [README, *PAGES] if p.name != 'results.md' for row in table_rows(p) if row in rows]
    assert not copied, f'rows of docs/results.md copied into other pages (link to the table instead): {copied[:3]}'


def test_pages_link_their_results_tables():
    """Every section of docs/results.md that holds a table is linked from another page."""
    linked = {t.split('#', 1)[1] for p in [README, *PAGES] if p.name != 'results.md'
              for t in links(p) if _relative(t) and t.split('#')[0].endswith('results.md') and '#' in t}
    results = DOCS / 'results.md'
    heading = None
    seen: dict[str, int] = {}
    with_table: list[str] = []
    for line in _prose(results.read_text()).split('\n'):
        match = _HEADING.match(line)
        if match:
            anchor = github_anchor(match.group(2))
            count = seen.get(anchor, 0)
            seen[anchor] = count + 1
            heading = anchor if count == 0 else f'{anchor}-{count}'
        elif _DELIMITER.match(line.strip()) and heading and heading not in with_table:
            with_table.append(heading)
    missing = [h for h in with_table if h not in linked]
    assert with_table
    assert not missing, f'result tables no other page links to: {missing}'
