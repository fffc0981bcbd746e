"""The packages' README benchmark tables have the rows and columns their benchmarks print."""
from __future__ import annotations

from pathlib import Path

from tools import sim_bench
from tools.detector_bench import run as detector_run

SRC = Path(__file__).resolve().parents[2] / 'ros2_ws' / 'src'


def _tables(text: str) -> list[tuple[str, list[list[str]]]]:
    """Markdown tables of ``text`` as (header line, rows of stripped cells)."""
    out: list[tuple[str, list[list[str]]]] = []
    lines = text.splitlines()
    for i, line in enumerate(lines[:-1]):
        if line.startswith('|') and lines[i + 1].startswith('|---'):
            rows = []
            for row in lines[i + 2:]:
                if not row.startswith('|'):
                    break
                rows.append([c.strip() for c in row.strip().strip('|').split('|')])
            out.append((line.strip(), rows))
    return out


def _section(path: Path, start: str, end: str) -> str:
    text = path.read_text()
    i = text.index(start)
    return text[i:text.index(end, i)]


def test_tables_are_parsed() -> None:
    text = 'x\n| a | b |\n|---|---|\n| 1 | 2 |\n| 3 |  |\n\n| c |\n|---|\n'
    assert _tables(text) == [('| a | b |', [['1', '2'], ['3', '']]), ('| c |', [])]


def test_sim_readme_rows_are_the_benchmarks() -> None:
    text = _section(SRC / 'icub_sim_bridge' / 'README.md', '## Benchmark', 'Rendering is about')
    (header, rows), = _tables(text)
    assert header == '| measure | value | target |'
    assert [(r[0], r[2]) for r in rows] == list(sim_bench.ROWS)


def test_detector_readme_tables_are_the_benchmarks() -> None:
    # A small study prints every table (both eyes and 640x480 included), with the same rows.
    printed = dict(_tables(detector_run(30, seed=0)))
    readme = _tables(_section(SRC / 'marker_detector' / 'README.md', '### Accuracy study', '### Tests'))
    assert len(readme) >= 4
    for header, rows in readme:
        assert header in printed, header
        labels = {r[0] for r in printed[header]}
        assert {r[0] for r in rows} <= labels, (header, labels)
