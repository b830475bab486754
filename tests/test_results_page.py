"""The results pages (results/<preset>/README.md) are what bench/experiments/results_page.py makes of the
committed tables, and README.md stays short and tells no result by hand."""
import re
from pathlib import Path

import pandas as pd
import pytest

from bench.experiments import results_page

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("folder", ["cpu", "cpu/val", "gpu", "paper"])
def test_the_committed_results_page_is_the_one_its_tables_give(folder):
    shown = f"results/{folder}"
    expected = results_page.page(ROOT / shown, results_page.preset_of(shown), shown_as=shown)
    assert (ROOT / shown / results_page.PAGE).read_text() == expected, (
        f"{shown}/README.md is stale: python -m bench.experiments.results_page {shown}")


def test_a_split_beside_the_presets_own_is_named_and_the_two_pages_link_each_other(tmp_path):
    caption = "Table 5. Preset cpu, split {}, 2000 training steps.\n\n| method |\n"
    table = pd.DataFrame({"method": ["Ours"], "PSNR": [36.5], "SSIM": [0.91], "relMSE": [0.016], "runs": ["a"]})
    for folder, split in ((tmp_path / "cpu", "test"), (tmp_path / "cpu" / "val", "val")):
        (folder / "sota").mkdir(parents=True)
        table.to_csv(folder / "sota" / "table.csv", index=False)
        (folder / "sota" / "table.md").write_text(caption.format(split))
    results_page.write(tmp_path / "cpu" / "val", "cpu", repository=tmp_path)
    results_page.write(tmp_path / "cpu", "cpu", repository=tmp_path)
    assert "(val/README.md)" in (tmp_path / "cpu" / results_page.PAGE).read_text()
    test = results_page.page(tmp_path / "cpu", "cpu", shown_as="results/cpu")
    assert test.startswith("# Results at preset `cpu`, split `test`") and "(val/README.md)" in test
    val = results_page.page(tmp_path / "cpu" / "val", "cpu", shown_as="results/cpu/val")
    assert val.startswith("# Results at preset `cpu`, split `val`") and "(../README.md)" in val
    assert "](../../../docs/decisions.md)" in val and "](../../docs/decisions.md)" in test
    assert results_page.preset_of("results/cpu/val") == "cpu" == results_page.preset_of("results/cpu")


def test_the_page_copies_its_numbers_from_the_tables_and_names_them(tmp_path):
    table = pd.DataFrame({"method": ["Input bilinear", "Ours"], "PSNR": [31.6856, 36.548], "PSNR std": [0.0, 0.1196],
                          "SSIM": [0.773, 0.9148], "SSIM std": [0.0, 0.0006], "relMSE": [0.1777, 0.01569],
                          "relMSE std": [0.0, 0.0009], "runs": ["a a a", "b c d"]})
    (tmp_path / "sota").mkdir()
    table.to_csv(tmp_path / "sota" / "table.csv", index=False)
    text = results_page.page(tmp_path, "mine", shown_as="results/mine")
    assert "[`results/mine/sota/table.csv`](sota/table.csv)" in text
    assert "| Ours | 3 | 36.55 ± 0.12 | 0.915 ± 0.00060 | 0.0157 ± 0.0009 |" in text
    assert "| Input bilinear | 1 | 31.69 | 0.773 | 0.1777 |" in text
    assert "Not judged at this preset" in text and "`deform`" in text   # no claims; the missing tables named


def test_a_study_of_kind_stability_is_counted_as_the_stability_table_is(tmp_path, monkeypatch):
    """A stability study (+study=emitters_stability) gets the stability table's counts, under its own name."""
    table = pd.DataFrame({"model": ["srd", "srd", "kpcn"], "case": ["clean", "lamp", "clean"],
                          "status": ["ok 2.7", "FAIL (lamp energy 113%)", "ok 3.4"], "max |output|": [2.7, 7e3, 3.4]})
    for name in ("stability", "studies/lamps"):
        (tmp_path / name).mkdir(parents=True)
        table.to_csv(tmp_path / name / "table.csv", index=False)
    monkeypatch.setattr(results_page, "KEPT_STUDIES", [("lamps", "Lamps in training.")])
    text = results_page.page(tmp_path, "mine", shown_as="results/mine")
    study = text[text.index("### studies/lamps"):]
    assert study.startswith("### studies/lamps\n\nLamps in training.\n\nEvery model on fireflies")
    assert "[`results/mine/studies/lamps/table.csv`](studies/lamps/table.csv)" in study
    assert "| srd | 2 | 1 | 0 | 1 | 0 | 7000.0 |" in study and "| kpcn | 1 | 1 | 0 | 0 | 0 | 3.4 |" in study
    assert text.count("### stability\n") == 1                    # the experiment's own section is still there


def test_readme_is_short_and_quotes_no_result():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    prose = re.sub(r"\[[^\]]*\]\([^)]*\)", "", readme)          # link texts may name a table's file
    assert not re.findall(r"\d\s*dB\b", prose), "a result typed by hand: link the results page instead"
    assert "results/cpu/README.md" in readme
    top = "\n".join(readme.splitlines()[:20])
    assert "make run" in top and "make test" in top                       # the two commands first


def test_docs_tell_no_result_and_no_dated_history():
    for page in (ROOT / "docs").glob("*.md"):
        text = re.sub(r"\[[^\]]*\]\([^)]*\)", "", page.read_text())
        assert not re.findall(r"\d\s*dB\b", text), f"{page.name}: a result typed by hand"
        assert not re.findall(r"\b20\d\d-\d\d-\d\d\b", text), f"{page.name}: dated history"
