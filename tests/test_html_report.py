"""The single-file HTML report (rendered in a real headless Chromium), and skipped cells grouped by reason in
every format, on hand-made records with a hostile model name and reason."""

from __future__ import annotations

import io
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console
from test_report import MIB, _metrics, _record

from bench_matrix.cell import Cell
from bench_matrix.report import write_report
from bench_matrix.report.analysis.summary import Report, summarize
from bench_matrix.report.render.columns import model_columns
from bench_matrix.report.render.html import page, write_html
from bench_matrix.report.render.html_parts import sort_value
from bench_matrix.report.render.markdown import model_page, page_name, write_pages
from bench_matrix.report.render.plots import Plot
from bench_matrix.report.render.terminal import print_report
from bench_matrix.report.render.text import NO_REASON, by_reason, skip_reason
from bench_matrix.store import CellRecord, ResultStore

NAME = '<b>evil</b> & "q"'  # user data: must show as text, never as markup
NO_GPU = "no NVIDIA GPU on this machine <script>alert(1)</script>\n  (no driver: nvidia-smi not found)"
NO_TRT = "TensorRT is not installed"
CUDA_LABELS = ["onnxruntime none fp16 cuda", "pytorch none fp16 cuda", "torchscript none fp16 cuda"]
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run"]


def _cell(backend: str, precision: str = "fp32", target: str = "cpu", model: str = NAME,
          strategy: str = "none") -> Cell:
    return Cell(model, "pytorch", backend, strategy, precision, target)


BASE = _cell("pytorch")
# (cell, p50 ms); as text, "12.5" would sort before "2.00"
TIMED = [(BASE, 2.0), (_cell("onnxruntime"), 1.0),
         (_cell("onnxruntime", "int8", strategy="ptq_dynamic"), 0.5),
         (_cell("torchscript"), 12.5)]


def _records() -> list[CellRecord]:
    """Four timed cells, one without latency, four skipped (two reasons), two failed with one headline, and a
    model measured on two hosts."""
    records = [_record(cell, metrics=_metrics(p50, 4.0 / p50, 0.012 + p50 / 1000)) for cell, p50 in TIMED]
    records.append(_record(_cell("openvino"), metrics={"size_bytes": MIB}))
    records += [_record(_cell(backend, "fp16", "cuda"), "skipped", NO_GPU)
                for backend in ("torchscript", "pytorch", "onnxruntime")]
    records.append(_record(_cell("tensorrt", "int8", "tensorrt"), "skipped", NO_TRT))
    records += [_record(_cell("tflite", p), "failed", f"RuntimeError: boom\n  File \"{p}.py\", line 1")
                for p in ("fp16", "int8")]
    for backend, host in (("pytorch", "bench-1"), ("onnxruntime", "bench-2")):
        records.append(_record(_cell(backend, model="tiny"), metrics=_metrics(0.4, 0.1, 0.05),
                               env={"host": host}))
    return records


INFOS: dict[str, dict[str, Any]] = {
    NAME: {"framework": "pytorch", "baseline_key": BASE.key, "test_mse": 0.014, "mean_predictor_mse": 0.06},
    "tiny": {"framework": "pytorch", "baseline_key": _cell("pytorch", model="tiny").key}}


@pytest.fixture
def report() -> Report:
    return summarize(_records(), INFOS, {})


def _png(path: Path) -> Path:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (40, 30), (200, 40, 40)).save(path)
    return path


def test_skipped_cells_are_grouped_by_reason_largest_group_first(report: Report) -> None:
    evil = report.models[0]
    groups = by_reason((*evil.skipped, _record(_cell("tvm"), "skipped", None)), skip_reason)
    assert [g.reason for g in groups] == [skip_reason(evil.skipped[0]), NO_REASON, NO_TRT]
    assert groups[0].reason == ("no NVIDIA GPU on this machine <script>alert(1)</script>\n"
                                "(no driver: nvidia-smi not found)")
    assert [r.cell.label for r in groups[0].records] == CUDA_LABELS  # cell-key order, not insertion order
    failed = by_reason(evil.failed, lambda r: r.reason.splitlines()[0])
    assert [(g.reason, len(g.records)) for g in failed] == [("RuntimeError: boom", 2)]


def test_markdown_and_terminal_give_each_skip_reason_once_with_its_cells(report: Report,
                                                                         tmp_path: Path) -> None:
    text = model_page(report.models[0], (), tmp_path)
    assert text.count("no NVIDIA GPU on this machine") == 1
    row = ("| no NVIDIA GPU on this machine &lt;script&gt;alert(1)&lt;/script&gt;<br>(no driver: "
           f"nvidia-smi not found) | 3 | {', '.join(CUDA_LABELS)} |")
    assert row in text and f"| {NO_TRT} | 1 | tensorrt none int8 tensorrt |" in text
    console = Console(record=True, width=200, color_system=None)
    print_report(report, console)
    shown = console.export_text()
    assert shown.count("no NVIDIA GPU on this machine") == 1
    assert "Skipped (4 cells, 2 distinct reasons)" in shown
    assert ", ".join(CUDA_LABELS) in shown


def test_a_host_column_only_where_a_models_cells_come_from_several_hosts(report: Report,
                                                                         tmp_path: Path) -> None:
    evil, tiny = report.models
    assert "Host" not in [c.header for c in model_columns(evil)]
    assert [c.header for c in model_columns(tiny)][:2] == ["Method", "Host"]
    text = model_page(tiny, (), tmp_path)
    assert "| Method | Host | Size MiB |" in text and "| onnxruntime none fp32 | bench-2 |" in text


def test_markdown_pages_embed_plots_relative_to_the_pages(report: Report, tmp_path: Path) -> None:
    plot = Plot("pareto", "Latency [vs] accuracy", _png(tmp_path / "plots" / "a b.png"), "chart of *cells*")
    paths = write_pages(report, tmp_path, {NAME: [plot]})
    text = paths[1].read_text()
    assert paths[1].name == page_name(NAME) and "/" not in page_name(NAME)
    assert "## Plots\n\n### Latency \\[vs\\] accuracy\n\n![chart of \\*cells\\*](plots/a%20b.png)" in text
    assert write_pages(report, tmp_path, {NAME: [plot]}) == paths and paths[1].read_text() == text


def test_page_names_are_plain_file_names() -> None:
    assert page_name("pilotnet") == "pilotnet.md" and page_name("Index") == "index-model.md"
    odd = [page_name(name) for name in ("a b/c", "a b c", "../x", ".hidden")]
    assert len(set(odd)) == 4 and all(re.fullmatch(r"[A-Za-z0-9_+-][A-Za-z0-9_.+-]*\.md", n) for n in odd)


@pytest.mark.parametrize(("text", "value"), [("2.00×", 2.0), ("1.00 ~", 1.0), ("+1.00e-04", 1e-4),
                                             ("-3", -3.0), ("0", 0.0), ("—", None), ("fp32 cpu", None)])
def test_sort_value_is_the_number_a_rendered_figure_starts_with(text: str, value: float | None) -> None:
    found = sort_value(text)
    assert (None if found is None else float(found)) == value


def test_html_escapes_user_text_and_refers_to_nothing_outside_the_file(report: Report,
                                                                        tmp_path: Path) -> None:
    plot = Plot("pareto", NAME, _png(tmp_path / "p.png"), '" onerror="alert(1)')
    text = page(report, {NAME: [plot]})
    assert "<b>evil</b>" not in text and "<script>alert" not in text and text.count("<script") == 1
    assert "<h2>&lt;b&gt;evil&lt;/b&gt; &amp; &quot;q&quot;</h2>" in text
    assert 'alt="&quot; onerror=&quot;alert(1)"' in text
    links = re.findall(r'(?:src|href)="([^"]*)"', text)
    assert links and all(link.startswith(("data:image/png;base64,", "#model-")) for link in links)
    assert not re.search(r"https?:|url\(|@import", text)
    path = write_html(report, {NAME: [plot]}, tmp_path / "out" / "report.html")
    assert path.read_text(encoding="utf-8") == text == page(report, {NAME: [plot]})  # byte-identical


# --- in a real browser ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    if not CHROMIUM.is_file():
        pytest.skip(f"no Chromium at {CHROMIUM}: apt-get install chromium (.ci/run installs it)")
    sync_api = pytest.importorskip("playwright.sync_api",
                                   reason="playwright is not installed: pip install -r requirements.lock")
    with sync_api.sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield launched
        launched.close()


@pytest.fixture(scope="module")
def report_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The HTML report of a store holding `_records()`, as `bench-matrix report --format html` writes it."""
    folder = tmp_path_factory.mktemp("html")
    store = ResultStore(folder / "results.sqlite")
    for record in _records():
        store.put(record)
    for name, info in INFOS.items():
        store.put_fact(f"model:{name}", "info", info)
    store.close()
    (path,) = write_report(folder / "results.sqlite", "html", folder / "out", Console(file=io.StringIO()))
    return path


@pytest.fixture
def shown(browser: Any, report_file: Path) -> Iterator[tuple[Any, list[str]]]:
    """The report open in a fresh page, and every URL the page requested."""
    tab = browser.new_page()
    requests: list[str] = []
    tab.on("request", lambda request: requests.append(request.url))
    tab.goto(report_file.as_uri())
    yield tab, requests
    tab.close()


def _column(table: Any, header: str) -> list[str]:
    index = table.locator("thead th").all_inner_texts().index(header)
    script = "(rows, i) => rows.map(r => r.cells[i].innerText.trim())"
    return table.locator("tbody tr").evaluate_all(script, index)


def _results(tab: Any, model: str) -> Any:
    section = tab.locator("section").filter(has=tab.get_by_role("heading", name=model, exact=True))
    return section.locator("table.sortable").first


def test_the_browser_shows_the_title_the_models_and_their_results(shown: tuple[Any, list[str]]) -> None:
    tab, _ = shown
    assert tab.title() == "bench-matrix report"
    for model in (NAME, "tiny"):
        assert tab.get_by_role("heading", name=model, exact=True).is_visible()
    assert tab.locator("h2 b").count() == 0  # the name's markup is text
    table = _results(tab, NAME)
    assert table.is_visible()
    methods = _column(table, "Method")
    assert methods[0] == "pytorch none fp32 (baseline)" and len(methods) == 5
    assert _column(_results(tab, "tiny"), "Host") == ["bench-1", "bench-2"]


def test_clicking_a_numeric_header_sorts_ascending_then_descending(shown: tuple[Any, list[str]]) -> None:
    tab, _ = shown
    table = _results(tab, NAME)
    assert _column(table, "p50 ms") == ["2.00", "0.500", "1.00", "12.5", "—"]
    table.locator("thead th", has_text="p50 ms").click()
    assert _column(table, "p50 ms") == ["0.500", "1.00", "2.00", "12.5", "—"]  # numerically; no value last
    table.locator("thead th", has_text="p50 ms").click()
    assert _column(table, "p50 ms") == ["12.5", "2.00", "1.00", "0.500", "—"]
    table.locator("thead th", has_text="Method").click()
    assert _column(table, "Method")[0] == "onnxruntime none fp32"


def test_plots_load_inline_and_nothing_but_the_file_is_requested(shown: tuple[Any, list[str]],
                                                                 report_file: Path) -> None:
    tab, requests = shown
    image = tab.locator("figure img").first
    assert image.is_visible() and image.evaluate("img => img.complete && img.naturalWidth") > 0
    assert image.get_attribute("src").startswith("data:image/png;base64,")
    assert requests and all(url == report_file.as_uri() or url.startswith("data:") for url in requests)


def test_skipped_and_failed_cells_show_grouped_by_reason(shown: tuple[Any, list[str]]) -> None:
    tab, _ = shown
    groups = tab.locator(".group.skipped")
    assert groups.count() == 2
    first = groups.first
    assert first.locator("pre").inner_text() == skip_reason(_record(BASE, "skipped", NO_GPU))
    assert first.locator("li").all_inner_texts() == CUDA_LABELS and first.is_visible()
    failed = tab.locator(".group.failed")
    assert failed.count() == 1 and failed.locator(".reason").inner_text() == "RuntimeError: boom"
    details = failed.locator("details").first
    assert not details.locator("pre").is_visible()
    details.locator("summary").click()
    assert 'File "fp16.py", line 1' in details.locator("pre").inner_text()
