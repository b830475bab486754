import pandas as pd

from bench.table_writer import listed_evaluations, read_table, write_table


def test_write_table_three_formats_with_best_in_bold(tmp_path):
    df = pd.DataFrame([
        {"method": "Input bilinear", "relMSE": 0.0648, "PSNR": 21.44, "SSIM": 0.41},
        {"method": "Ours", "relMSE": 0.0055, "PSNR": 32.11, "SSIM": 0.86},
        {"method": "Ours (paper)", "relMSE": 0.0001, "PSNR": 99.0, "SSIM": 0.99, "compete": False},
    ])
    df.loc[:1, "compete"] = True
    paths = write_table(df, tmp_path / "t", caption="A caption with x^2 and a_b",
                        lower_is_better=("relMSE",), higher_is_better=("PSNR", "SSIM"))
    csv = pd.read_csv(paths["csv"])
    assert list(csv.columns) == ["method", "relMSE", "PSNR", "SSIM"]
    assert csv["relMSE"].iloc[1] == 0.0055
    md = paths["md"].read_text()
    assert "relMSE \u2193" in md and "PSNR \u2191" in md
    assert "**0.0055**" in md and "**32.1100**" in md and "**0.0001**" not in md
    tex = paths["tex"].read_text()
    assert r"\toprule" in tex and r"\bottomrule" in tex and r"$\downarrow$" in tex
    assert r"\textbf{0.0055}" in tex and r"x\^{}2" in tex and r"a\_b" in tex


def test_infinite_psnr_is_printed_not_nan(tmp_path):
    df = pd.DataFrame([{"method": "identity", "relMSE": 0.0, "PSNR": float("inf"), "SSIM": 1.0}])
    md = write_table(df, tmp_path, higher_is_better=("PSNR",))["md"].read_text()
    assert "inf" in md and "nan" not in md.lower()


def test_seed_std_and_sequence_se_are_printed_inside_their_cells(tmp_path):
    df = pd.DataFrame([{"method": "Ours", "PSNR": 34.5, "PSNR std": 0.1, "PSNR se": 0.25, "SSIM": 0.9,
                        "SSIM se": 0.02}])
    paths = write_table(df, tmp_path, higher_is_better=("PSNR", "SSIM"))
    md = paths["md"].read_text()
    assert "34.5000 \u00b1 0.1000 (se 0.2500)" in md and "0.9000 (se 0.0200)" in md
    assert "PSNR se" not in md.splitlines()[0]
    assert list(pd.read_csv(paths["csv"]).columns) == ["method", "PSNR", "PSNR std", "PSNR se", "SSIM", "SSIM se"]


def test_a_rows_runs_cell_reads_back_one_evaluation_per_seed(tmp_path):
    df = pd.DataFrame([{"method": "Ours", "runs": "a1 b2 c3"}, {"method": "OIDN", "runs": "d4 d4 d4"},
                       {"method": "paper", "runs": None}])
    df.to_csv(tmp_path / "table.csv", index=False)
    cells = read_table(tmp_path / "table.csv")["runs"]          # an empty cell reads back as NaN
    assert [listed_evaluations(c) for c in cells] == [["a1", "b2", "c3"], ["d4"] * 3, []]
    pd.DataFrame([{"method": "one seed", "runs": "0123456789012345"}]).to_csv(tmp_path / "digits.csv", index=False)
    assert listed_evaluations(read_table(tmp_path / "digits.csv")["runs"].iloc[0]) == ["0123456789012345"]
    assert pd.read_csv(tmp_path / "digits.csv")["runs"].iloc[0] == 123456789012345   # what read_table avoids
