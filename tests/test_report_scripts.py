"""Scripts that read eval reports, datasets or saved outputs (scripts/compare_on_valscenes.py, scripts/bright_share_vs_ratio.py,
scripts/ratio_by_lighting.py,
scripts/results_block_drift.py, scripts/dataset_fingerprint.py,
scripts/error_bands.py, scripts/two_scale_probe.py, scripts/loss_balance.py, scripts/band_probe.py,
scripts/guide_swap_probe.py, scripts/gap_by_feature.py, scripts/demod_probe.py,
scripts/bias_variance_probe.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from repo_scripts import load_script


def _report(path: Path, folder: str, scenes: list[str], seeds: list[int], value: float) -> Path:
    rows = [{"image": f"{folder}{s}_128x128_d8_spp16_seed{seed}", "spp": 4, "method": m, "relmse": value * (i + 1),
             "psnr": 30.0 - i} for i, s in enumerate(scenes) for seed in seeds for m in ("old", "new")]
    path.write_text(json.dumps({"rows": rows}))
    return path


def test_compare_on_valscenes_keeps_scenes_apart_under_any_folder(tmp_path: Path) -> None:
    """Catches the scene key taken from the whole image path up to its first "_": images under
    `--data data/scene_inputs` then all became one scene "scene", the first image's figures stood for
    every scene, and the printed means were one scene's (it happened in campaign 25)."""
    cmp = load_script("compare_on_valscenes")
    scenes, seeds = ["bathroom", "salle-de-bain", "teapot-full"], [7, 8]
    for folder in ("", "scene_inputs/", "data/my_inputs/"):
        d = cmp.collect([str(_report(tmp_path / "r.json", folder, scenes, seeds, 0.1))])
        assert sorted(d) == sorted((s, seed, 4) for s in scenes for seed in seeds), folder
        assert d[("teapot-full", 8, 4)]["new"] == (0.1 * 3, 28.0)


def test_compare_on_valscenes_first_report_wins(tmp_path: Path) -> None:
    """Catches a later report overwriting a model's rows from an earlier one (the documented order)."""
    cmp = load_script("compare_on_valscenes")
    a = _report(tmp_path / "a.json", "x_y/", ["lamp"], [7], 0.1)
    b = _report(tmp_path / "b.json", "x_y/", ["lamp"], [7], 0.5)
    assert cmp.collect([str(a), str(b)])[("lamp", 7, 4)]["old"][0] == 0.1
    assert cmp.collect([str(b), str(a)])[("lamp", 7, 4)]["old"][0] == 0.5


def test_compare_on_valscenes_exclude_drops_a_scene_from_every_mean(tmp_path: Path, monkeypatch, capsys) -> None:
    """Catches --exclude that filters only one printed figure (the means would still hold the scene),
    matches scene names by substring (teapot would drop teapot-full), or silently ignores a misspelt
    scene (a mean "without" it would be the full mean)."""
    import pytest

    cmp = load_script("compare_on_valscenes")
    rep = _report(tmp_path / "r.json", "scene_inputs/", ["bathroom", "teapot", "teapot-full"], [7], 0.1)
    monkeypatch.setattr("sys.argv", ["compare_on_valscenes.py", str(rep), "old", "new", "--exclude", "teapot"])
    cmp.main()
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "without teapot:"
    # old's relMSE is 0.1 * (1, 2, 3) over the three scenes: without teapot (2), mean (0.1 + 0.3) / 2.
    assert out[1].split()[:5] == ["4", "spp", "old", "relMSE", "0.20000"]
    assert "        new better than old on 0/2 scene renderings" in out  # two renderings left, not three
    monkeypatch.setattr("sys.argv", ["compare_on_valscenes.py", str(rep), "old", "new", "--exclude", "teapots"])
    with pytest.raises(SystemExit):
        cmp.main()
    assert "no scene teapots" in capsys.readouterr().err


def test_bright_share_and_spearman() -> None:
    """Catches a share taken over the darkest pixels or per channel instead of luminance, and a rank
    correlation that is not invariant to monotone maps (or has the wrong sign)."""
    import numpy as np

    bs = load_script("bright_share_vs_ratio")
    img = np.full((8, 8, 3), 1.0)
    img[2, 3] = (97.0, 97.0, 97.0)  # one small bright light: 97 of the image's 160 units of luminance
    assert bs.bright_share(img, 1) == np.float64(97.0 / 160.0)
    img[5, 5] = (0.0, 3.0, 0.0)  # luminance 1, the same as its neighbours: the share of one pixel stays put
    assert abs(bs.bright_share(img, 1) - 97.0 / 160.0) < 1e-12
    assert bs.bright_share(np.zeros((4, 4, 3)), 2) == 0.0
    x = np.array([0.1, 0.5, 0.2, 0.9, 0.3])
    assert abs(bs.spearman(x, np.exp(5 * x)) - 1.0) < 1e-12
    assert abs(bs.spearman(x, -x ** 3) + 1.0) < 1e-12


def test_compare_on_valscenes_scene_ratios_average_seeds_before_dividing(tmp_path: Path) -> None:
    """Catches a per-scene ratio taken per rendering and then averaged (or over the wrong scene's
    renderings): NEW / OLD must be the ratio of the two means over the seeds."""
    cmp = load_script("compare_on_valscenes")
    sc = {("bath", 7): {"old": (1.0, 0.0), "new": (2.0, 0.0)}, ("bath", 8): {"old": (3.0, 0.0), "new": (2.0, 0.0)},
          ("lamp", 7): {"old": (0.5, 0.0), "new": (0.25, 0.0)}}
    assert cmp.scene_ratios(sc, "old", "new") == {"bath": 1.0, "lamp": 0.5}


def _meta(kind: str, window: bool, bulbs: int) -> dict:
    return {"extra": {"procedural": {"kind": kind, "rich": {"window": window, "small_emitters": bulbs, "night": False}}}}


def _lighting_report(tmp_path: Path, values: list[float], rows_of) -> Path:
    """An eval report over three procedural images (one with bulbs, two outdoor without), the
    image ``i``'s rows from ``rows_of(i, values[i])``."""
    images, rows = [], []
    for i, (meta, v) in enumerate(zip([_meta("indoor", True, 3), _meta("outdoor", False, 0),
                                       _meta("outdoor", False, 0)], values)):
        d = tmp_path / f"im{i}"
        d.mkdir()
        (d / "meta.json").write_text(json.dumps(meta))
        images.append({"id": f"im{i}", "path": str(d)})
        rows += rows_of(i, v)
    report = tmp_path / "results.json"
    report.write_text(json.dumps({"images": images, "rows": rows}))
    return report


def test_ratio_by_lighting_groups_and_geometric_means(tmp_path: Path, monkeypatch, capsys) -> None:
    """Catches bulbs counted from the wrong field (every rich image would be "bulbs"), a classic or
    scene-file image sent to a procedural group, an arithmetic mean of ratios (one outlier image would
    hold the group), and rows of other spp or methods mixed into a group."""
    rl = load_script("ratio_by_lighting")
    assert rl.lighting_group(_meta("indoor", True, 0)) == "no bulbs"
    assert rl.lighting_group(_meta("indoor", True, 2), detail=True) == "window, bulbs"
    assert rl.lighting_group(_meta("indoor", False, 0), detail=True) == "lamps, no bulbs"
    assert rl.lighting_group(_meta("outdoor", False, 1), detail=True) == "outdoor, bulbs"
    assert rl.lighting_group({"extra": {"procedural": {"kind": "indoor"}}}) == "no bulbs"  # classic world
    assert rl.lighting_group({"extra": {}}) == "scene file"
    n, g = rl.geo_ratios({"a": [(4.0, 1.0), (1.0, 4.0)]})["a"]
    assert n == 2 and abs(g - 1.0) < 1e-12  # arithmetic: 2.125

    report = _lighting_report(tmp_path, [0.5, 2.0, 8.0], lambda i, ratio: [
        {"image": f"im{i}", "spp": 4, "method": "old", "relmse": 0.1},
        {"image": f"im{i}", "spp": 4, "method": "new", "relmse": 0.1 * ratio},
        {"image": f"im{i}", "spp": 8, "method": "new", "relmse": 99.0},
        {"image": f"im{i}", "spp": 4, "method": "other", "relmse": 99.0}])
    monkeypatch.setattr("sys.argv", ["ratio_by_lighting.py", str(report), "old", "new", "--spp", "4"])
    rl.main()
    line = capsys.readouterr().out.splitlines()[-1].split()
    assert line[:2] == ["4", "new"]
    assert line[2:] == ["0.5000", "(n=1)", "4.0000", "(n=2)"]
    monkeypatch.setattr("sys.argv", ["ratio_by_lighting.py", str(report), "old", "new", "--spp", "4", "--all"])
    rl.main()
    # Catches an "all images" column that leaves a group out or counts an image twice: (0.5 * 2 * 8) ** (1/3).
    assert capsys.readouterr().out.splitlines()[-1].split()[-2:] == ["2.0000", "(n=3)"]


def test_ratio_by_lighting_by_noise_groups_by_the_noisy_input(tmp_path: Path, monkeypatch, capsys) -> None:
    """Catches quartiles ranked the wrong way (q1 must be the least noisy), taken from another spp's
    noisy rows (noise falls with spp, so groups would shift), groups that lose or repeat an image, and
    the lighting groups printed instead."""
    rl = load_script("ratio_by_lighting")
    group, edges = rl.noise_quartiles({f"i{k}": float(v) for k, v in enumerate([8, 1, 7, 2, 6, 3, 5, 4])})
    assert [group[f"i{k}"] for k in (1, 3, 5, 7, 6, 4, 2, 0)] == \
        ["noise q1", "noise q1", "noise q2", "noise q2", "noise q3", "noise q3", "noise q4", "noise q4"]
    assert edges == [1.0, 3.0, 5.0, 7.0, 8.0]
    assert sorted(rl.noise_quartiles({"a": 1.0, "b": 2.0, "c": 3.0})[0].values()) == ["noise q1", "noise q2", "noise q3"]
    # Three images: at 4 spp the least noisy has ratio 0.5; at 8 spp the noise order is reversed.
    report = _lighting_report(tmp_path, [0.5, 2.0, 8.0], lambda i, ratio: [
        {"image": f"im{i}", "spp": 4, "method": "noisy", "relmse": 1.0 + i},
        {"image": f"im{i}", "spp": 8, "method": "noisy", "relmse": 10.0 - i},
        {"image": f"im{i}", "spp": 4, "method": "old", "relmse": 0.1},
        {"image": f"im{i}", "spp": 4, "method": "new", "relmse": 0.1 * ratio}])
    monkeypatch.setattr("sys.argv", ["ratio_by_lighting.py", str(report), "old", "new", "--spp", "4", "--by-noise", "--all"])
    rl.main()
    out = capsys.readouterr().out.splitlines()
    assert "noise q1" in out[1] and "bulbs" not in out[1]
    assert out[2].split() == ["4", "new", "0.5000", "(n=1)", "2.0000", "(n=1)", "8.0000", "(n=1)", "2.0000", "(n=3)"]
    assert out[-1] == "noisy relMSE at 4 spp, quartile edges: 1 / 2 / 3 / 3"


def test_ratio_by_lighting_psnr_mode(tmp_path: Path, monkeypatch, capsys) -> None:
    """Catches a PSNR mode that reads the relMSE field, takes OLD - NEW (a loss printed as a gain),
    counts the images where NEW is lower wrong, or prints fewer than the 5 decimals at which a
    campaign's tie was decided."""
    rl = load_script("ratio_by_lighting")
    assert rl.psnr_differences({"a": [(30.0, 30.5), (28.0, 27.0)]})["a"] == (2, 0.25, 1)
    report = _lighting_report(tmp_path, [29.0, 31.5, 29.5], lambda i, new_db: [
        {"image": f"im{i}", "spp": 4, "method": "old", "relmse": 0.1, "psnr": 30.0},
        {"image": f"im{i}", "spp": 4, "method": "new", "relmse": 0.3, "psnr": new_db}])
    monkeypatch.setattr("sys.argv", ["ratio_by_lighting.py", str(report), "old", "new", "--spp", "4", "--metric", "psnr"])
    rl.main()
    line = capsys.readouterr().out.splitlines()[-1].split()
    assert line == ["4", "new", "-1.00000", "dB", "(1/1", "lower)", "+0.50000", "dB", "(1/2", "lower)"]


def test_results_block_drift_reads_the_committed_block_and_flags_worse_than_noisy(tmp_path: Path) -> None:
    """Catches a drift check that parses the wrong table (the means table as per-image values, or the
    bold marks as text), pairs images by their full path instead of the scene, or that misses a model
    worse than the noisy input in PSNR only."""
    import numpy as np

    drift = load_script("results_block_drift")
    lines = drift.block_lines(Path("docs/RESULTS.md"), "valscenes")
    means, per = drift.parse_block(lines)
    # The committed block: 4 means rows per spp for OIDN and noisy, nine scenes per spp and method.
    assert means[("noisy", 4)][0] > means[("oidn-high", 4)][0] > 0
    assert sum(1 for (m, s, _) in per if m == "layer-medium" and s == 8) == 9
    assert per[("combine-ens_kpcn", 4, "bathroom")] > 0  # a bold cell parses
    rows = [{"image": f"data/scene_inputs/{im}_128x128_d8_spp16_seed7", "spp": s, "method": m,
             "relmse": v * (1.01 if m == "layer-medium" else 1.0), "psnr": 20.0 if m == "noisy" else 25.0}
            for (m, s, im), v in per.items()]
    rows = [r for r in rows if not (r["method"] == "wskp" and r["spp"] == 16 and r["image"].find("/lamp_") > 0)]
    rows.append({"image": "data/scene_inputs/lamp_128x128_d8_spp16_seed7", "spp": 16, "method": "wskp",
                 "relmse": per[("wskp", 16, "lamp")], "psnr": 19.0})
    (tmp_path / "r.json").write_text(json.dumps({"rows": rows}))
    import contextlib
    import io
    import sys

    out = io.StringIO()
    argv, sys.argv = sys.argv, ["x", str(tmp_path / "r.json")]
    try:
        with contextlib.redirect_stdout(out):
            drift.main()
    finally:
        sys.argv = argv
    text = out.getvalue()
    lm8 = next(s for s in text.splitlines() if s.startswith("layer-medium") and " 8 |" in s)
    assert "+1.00%" in lm8 and "1.00e-02, 1.00e-02" in lm8, lm8
    kp4 = next(s for s in text.splitlines() if s.startswith("kpcn ") and " 4 |" in s)
    assert "0.00e+00, 0.00e+00" in kp4, kp4
    assert "  wskp 16 spp: lamp_128x128_d8_spp16_seed7 PSNR 19.00 <= 20.00\n" in text and "worse than the noisy input" in text
    assert text.count(" spp: ") == 1, text  # the block's own models beat noisy in relMSE everywhere
    assert np.isfinite(means[("layer-medium", 16)][1])


def _run_drift(drift, report: Path, section: str) -> str:
    import contextlib
    import io
    import sys

    out = io.StringIO()
    argv, sys.argv = sys.argv, ["x", str(report), "--section", section]
    try:
        with contextlib.redirect_stdout(out):
            drift.main()
    finally:
        sys.argv = argv
    return out.getvalue()


def test_results_block_drift_averages_every_seed_and_pairs_no_image_it_cannot_name(tmp_path: Path) -> None:
    """Catches the six-seed mis-pairing of campaign 32: report rows keyed by scene, so the six seeds of a
    scene overwrote each other, the "new" means were one seed's, and a seed-12 image was compared with the
    seed-7 block's row (nan or wrong per-image drift); and the procedural block's repeated "proc" rows
    read as one image."""
    import numpy as np

    drift = load_script("results_block_drift")
    means, per = drift.parse_block(drift.block_lines(Path("docs/RESULTS.md"), "valscenes"))
    scenes = sorted({im for (_, _, im) in per})
    rows, values = [], []
    for k, im in enumerate(scenes):
        for seed in range(7, 13):
            for m in ("noisy", "layer-medium"):
                v = (1.0 if m == "noisy" else 0.01) * (k + 1) * seed
                rows.append({"image": f"data/scene_inputs/{im}_128x128_d8_spp16_seed{seed}", "spp": 4, "method": m,
                             "relmse": v, "psnr": 20.0 if m == "noisy" else 25.0})
                if m == "layer-medium":
                    values.append(v)
    (tmp_path / "r.json").write_text(json.dumps({"rows": rows}))
    text = _run_drift(drift, tmp_path / "r.json", "valscenes")
    lm4 = next(s for s in text.splitlines() if s.startswith("layer-medium") and " 4 |" in s)
    assert f"-> {np.mean(values):.4g} " in lm4 and "no image pairs" in lm4, lm4
    assert "(0 of the report's 54 images paired" in text, text
    # The procedural block's per-image rows are all "proc": none is taken as an image.
    _, per_proc = drift.parse_block(drift.block_lines(Path("docs/RESULTS.md"), "procedural-test"))
    assert not any(im == "proc" for (_, _, im) in per_proc)


def test_dataset_fingerprint_compares_per_image_and_names_what_differs(tmp_path: Path, capsys) -> None:
    """Catches a comparison that passes when one image's pixels differ (a re-rendered held-out set
    on another CPU would then be called identical), that counts a writer's hidden temporary folder,
    or that cannot say which file differs."""
    import sys

    fp = load_script("dataset_fingerprint")
    root = tmp_path / "ds"
    for name, noisy in (("proc_000000", 11), ("proc_000001/view_000", 12), (".proc_000002.tmp", 13)):
        (root / name).mkdir(parents=True)
        (root / name / "meta.json").write_text(json.dumps({"checksums": {
            "algorithm": "crc32", "samples_blocks": {"offset": 0, "crc": 5}, "samples_header": 6,
            "noisy.exr": noisy, "reference.exr": 7}}))
    prints = fp.fingerprints(root)
    assert sorted(prints) == ["ds/proc_000000", "ds/proc_000001/view_000"]
    saved = tmp_path / "fp.txt"
    saved.write_text("".join(f"{k} {v}\n" for k, v in prints.items()))
    argv = sys.argv
    try:
        sys.argv = ["x", str(root), "--compare", str(saved)]
        assert fp.main() == 0
        assert "2 of 2 images identical" in capsys.readouterr().out
        meta = root / "proc_000001" / "view_000" / "meta.json"
        doc = json.loads(meta.read_text())
        doc["checksums"]["noisy.exr"] = 99
        meta.write_text(json.dumps(doc))
        assert fp.main() == 1
        out = capsys.readouterr().out
        assert "differs: ds/proc_000001/view_000 (noisy)" in out and "1 of 2 images identical, 1 differ" in out
    finally:
        sys.argv = argv


def test_error_bands_block_means_keep_only_coarse_error() -> None:
    """Catches block means taken over the wrong axes (channels mixed, or rows with columns), and a
    band score that does not separate fine noise (zero-mean inside a block: vanishes at k = 2) from a
    coarse offset (kept at every k)."""
    import numpy as np

    eb = load_script("error_bands")
    img = np.arange(2 * 4 * 6, dtype=np.float64).reshape(2, 4, 6)
    bm = eb.block_mean(img, 2)
    assert bm.shape == (2, 2, 3) and bm[1, 1, 2] == img[1, 2:4, 4:6].mean()
    y = np.ones((3, 8, 8))
    checker = np.indices((8, 8)).sum(axis=0) % 2 * 2 - 1.0  # +-1, mean 0 in every 2x2 block
    noisy = y + 0.1 * checker
    assert eb.band_relmse(noisy, y, 1) > 0 and eb.band_relmse(noisy, y, 2) < 1e-20
    offset = y * 1.1
    r = [eb.band_relmse(offset, y, k) for k in (1, 2, 4, 8)]
    assert np.allclose(r, r[0]) and r[0] > 0


def test_error_bands_keeps_images_of_the_same_folder_name_apart(tmp_path: Path) -> None:
    """Catches images keyed by their last folder's name: the views of a held-out dataset
    (``detail_ref/proc_000031/view_000``) and the scenes of two datasets share names, and 46 held-out
    images were scored as 10, the last of each name standing for the others (campaign 32)."""
    import numpy as np

    from mcdenoise.io.exr import write_exr

    eb = load_script("error_bands")
    ref = np.ones((3, 4, 4), dtype=np.float32)
    folders = ["a/proc_0/view_000", "a/proc_0/view_001", "b/proc_0/view_000"]
    for i, f in enumerate(folders):
        d = tmp_path / "images" / f
        (d / "4spp").mkdir(parents=True)
        write_exr(d / "reference.exr", {"radiance": ref})
        write_exr(d / "4spp" / "x.exr", {"radiance": ref * (1 + 0.1 * (i + 1))})
        write_exr(d / "4spp" / "y.exr", {"radiance": ref})
    data = eb.collect(tmp_path, ["x", "y"], [1])
    assert sorted(data[4]) == folders
    got = [data[4][f]["x"][0] for f in folders]
    assert np.allclose(got, [(0.1 * (i + 1)) ** 2 / 1.01 for i in range(3)])


def test_band_probe_prefers_the_noisy_band_where_the_base_is_biased(tmp_path: Path) -> None:
    """Catches a probe that scores the wrong image against the reference (base and candidate
    swapped, or the noisy mean scored as the base): a base 30% too bright everywhere, and a noisy
    mean that is the reference plus zero-mean checker noise, must give a band candidate better than
    the base on every image, and counts of images out of the number read."""
    import numpy as np

    from mcdenoise.io.exr import write_exr

    bp = load_script("band_probe")
    checker = (np.indices((32, 32)).sum(axis=0) % 2 * 2 - 1.0).astype(np.float32)
    for i in range(2):
        ref = np.full((3, 32, 32), 0.2 + 0.1 * i, dtype=np.float32)
        d = tmp_path / "images" / f"set/img_{i}"
        (d / "4spp").mkdir(parents=True)
        write_exr(d / "reference.exr", {"radiance": ref})
        write_exr(d / "4spp" / "m.exr", {"radiance": ref * 1.3})
        write_exr(d / "4spp" / "noisy.exr", {"radiance": ref * (1 + 0.5 * checker)})
    res = bp.score(tmp_path, "m", 4, [4], [4.0])
    assert sorted(res) == ["base", "f4 c4"] and len(res["base"]) == 2
    assert all(c[0] < b[0] / 10 and c[1] > b[1] for b, c in zip(res["base"], res["f4 c4"]))
    assert "2/2" in bp.table("r", res)[-1]


def test_two_scale_probe_merges_blocks_and_keeps_a_consistent_image() -> None:
    """Catches a 2x2 merge that mixes pixels of other blocks or leaves sub-pixel positions in the
    small pixel's frame (the half-resolution pass would then see samples at the wrong places), and a
    band swap that changes an image whose half-resolution version is its own 2x2 mean."""
    import numpy as np
    import torch

    ts = load_script("two_scale_probe")
    rad = torch.arange(16.0).view(1, 1, 1, 4, 4)
    sub = torch.stack([torch.full((4, 4), 0.25), torch.full((4, 4), 0.75)]).view(1, 1, 2, 4, 4)
    m = ts.merge_2x2({"radiance": rad, "subpixel": sub, "scene_features": torch.zeros(1, 5)})
    assert m["radiance"].shape == (1, 4, 1, 2, 2)
    assert m["radiance"][0, :, 0, 0, 0].tolist() == [0.0, 1.0, 4.0, 5.0]
    assert m["radiance"][0, :, 0, 1, 1].tolist() == [10.0, 11.0, 14.0, 15.0]
    assert m["subpixel"][0, :, :, 0, 0].tolist() == [[0.125, 0.375], [0.625, 0.375], [0.125, 0.875], [0.625, 0.875]]
    assert torch.equal(m["scene_features"], torch.zeros(1, 5))
    full = np.random.default_rng(0).random((3, 8, 8)).astype(np.float32)
    half = full.reshape(3, 4, 2, 4, 2).mean(axis=(2, 4))
    assert np.abs(ts.two_scale(full, half) - full).max() < 1e-6
    assert ts.two_scale(full, half + 0.5).mean() > full.mean() + 0.45  # the coarse band is the half one's


def test_loss_balance_ratios_and_powers_of_two(tmp_path: Path, monkeypatch, capsys) -> None:
    """Catches an inverted ratio (the weight that would make the new term 1/ratio as large), a
    guided loss called without the input's guide (a crash), and means over a different number of
    crops than asked: a term against itself is exactly 1, and the printed means give the ratio."""
    from train_tiny_data import make_tiny_dataset

    data = make_tiny_dataset(tmp_path / "data", train=2, val=0, spp=4, size=24)
    lb = load_script("loss_balance")
    monkeypatch.setattr("sys.argv", ["loss_balance.py", "layer-small", str(data), "--terms", "smape", "tonemapped_l2",
                                     "relmse_in", "smape", "--crop", "16", "--spp", "2", "--crops", "4", "--batch", "2"])
    lb.main()
    out = capsys.readouterr().out.splitlines()
    assert "on 4 crops" in out[0]
    rows = [line.split() for line in out[1:]]
    means = [float(r[2]) for r in rows]
    ratios = [float(r[r.index("smape:") + 1]) for r in rows]
    assert ratios[0] == 1.0 and ratios[3] == 1.0 and means[3] == means[0]
    for m, r in zip(means[1:3], ratios[1:3]):
        assert abs(r - means[0] / m) <= 1e-3 * r  # printed to 4 significant digits


def test_per_sample_vs_pixel_averages_every_rendering_of_a_scene(tmp_path: Path, monkeypatch, capsys) -> None:
    """Catches the six-seed collapse: rows keyed by scene alone, so each scene's last seed overwrote the
    others, the printed means were one seed's (0.0890 for OIDN high where the report's mean over 54
    renderings was 0.0981) and a scene's verdict was that seed's; and the scene taken from the whole path
    ("data/scene" for every image under data/scene_inputs)."""
    import csv
    import sys

    pvp = load_script("per_sample_vs_pixel")
    values = {  # (scene, seed) -> relMSE of layer, kpcn-pixel, oidn-high: seed 8 alone would flip bathroom
        ("bathroom", 7): (1.0, 3.0, 2.0), ("bathroom", 8): (1.0, 0.5, 0.5),
        ("lamp", 7): (0.2, 0.1, 0.1), ("lamp", 8): (0.2, 0.1, 0.1),
    }
    path = tmp_path / "results.csv"
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["image", "spp", "method", "relmse"])
        w.writeheader()
        for (sc, seed), vals in values.items():
            for m, v in zip(("layer", "kpcn-pixel", "oidn-high"), vals):
                w.writerow({"image": f"data/scene_inputs/{sc}_128x128_d8_spp16_seed{seed}", "spp": 4, "method": m,
                            "relmse": v})
    monkeypatch.setattr(sys, "argv", ["x", str(path), "--sample", "layer"])
    pvp.main()
    out = capsys.readouterr().out
    assert "| bathroom | 4 | 0.57 | 0.80 |" in out, out  # 2.0 / 3.5 and 2.0 / 2.5: means over both seeds
    assert "| lamp | 4 | 2.00 | 2.00 |" in out, out
    assert "better than kpcn-pixel on 1, than OIDN high on 1 of 2 scenes (1 and 1 of 4 renderings" in out, out
    assert "mean relMSE 0.6000)" in out and "kpcn-pixel 0.9250, OIDN high 0.6750" in out, out


def test_training_evidence_counts_the_crops_of_every_member_of_an_ensemble() -> None:
    """Catches a card whose command holds two trainings (refine-layer_medium_ctx_x2's members) counted
    as one: its seen megapixels would be half of what trained it."""
    ev = load_script("training_evidence")
    one = "mcdenoise train --model refine --data d --steps 800 --batch 8 --crop 96"
    assert ev.seen_mp(one) == 800 * 8 * 96 * 96 / 1e6
    two = f"{one}  # seed 0; then  {one} --seed 1  # seed 1; then  python scripts/refine_ensemble.py a b c"
    assert ev.seen_mp(two) == 2 * ev.seen_mp(one)


def test_guide_swap_probe_replaces_only_the_named_guides_by_their_means() -> None:
    """Catches a swap that touches the radiance (the probe would measure something else), one that
    keeps a sample's own guide, a mean over the wrong axis, or a shape the model cannot read."""
    gs = load_script("guide_swap_probe")
    rng = np.random.default_rng(0)
    full = {c: rng.random((16, 3, 4, 5)).astype(np.float32) for c in ("albedo", "normal")}
    batch = {"radiance": torch.rand(1, 4, 3, 4, 5), "albedo": torch.from_numpy(full["albedo"][:4])[None],
             "normal": torch.from_numpy(full["normal"][:4])[None]}
    out = gs.swap_to_means(batch, full, ("albedo",))
    assert out["radiance"] is batch["radiance"] and out["normal"] is batch["normal"]
    assert out["albedo"].shape == batch["albedo"].shape
    want = torch.from_numpy(full["albedo"].mean(0))
    for k in range(4):
        assert torch.allclose(out["albedo"][0, k], want)


def test_gap_by_feature_puts_each_error_in_its_bin_and_weighs_images_alike(tmp_path: Path, monkeypatch, capsys) -> None:
    """Catches a feature read from the wrong dataset folder (the report's first folder is the dataset's name, the
    dataset's is not), bins that drop or double-count pixels, and images weighted by their own error (one noisy image
    then decides the table): A's error is 3x B's on the textured half of one image and equal to B's elsewhere and on
    the other image, whose errors are 10x larger; weighed alike, the textured bin's ratio is (3 + 1) / 2."""
    from mcdenoise.io.exr import write_exr

    gb = load_script("gap_by_feature")
    h, w = 4, 8
    ref = np.ones((3, h, w), dtype=np.float32)
    albedo = np.full((3, h, w), 0.5, dtype=np.float32)
    albedo[:, :, 4:] = np.where(np.indices((h, 4)).sum(axis=0) % 2 == 0, 0.2, 0.8)  # textured right half
    for i, scale in enumerate((1.0, 10.0)):
        d = tmp_path / "rep" / "images" / "ds" / f"img{i}"
        (d / "4spp").mkdir(parents=True)
        write_exr(d / "reference.exr", {"radiance": ref})
        b = ref + 0.1 * np.sqrt(scale)
        a = b.copy()
        if i == 0:
            a[:, :, 4:] = ref[:, :, 4:] + 0.1 * np.sqrt(3 * scale)
        write_exr(d / "4spp" / "A.exr", {"radiance": a})
        write_exr(d / "4spp" / "B.exr", {"radiance": b})
        n = tmp_path / "ds" / f"img{i}"
        n.mkdir(parents=True)
        write_exr(n / "noisy.exr", {"radiance": ref, "albedo": albedo, "roughness": np.ones((1, h, w), np.float32),
                                    "depth": np.ones((1, h, w), np.float32), "normal": np.ones((3, h, w), np.float32)})
    gb.main([str(tmp_path / "rep"), str(tmp_path / "ds"), "A", "B"])
    out = capsys.readouterr().out
    tex = out.split("albedo_texture:")[1].split("\n\n")[0].splitlines()
    rows = {r.split("|")[0].strip(): [float(v) for v in r.split("|")[1:]] for r in tex[1:]}
    # Column 3 borders the texture (its neighbour differs by 0.3): the middle bin, with no extra error.
    assert rows["[0, 0.01)"][0] == 0.375 and np.isclose(rows["[0, 0.01)"][3], 1.0, rtol=1e-4)
    assert rows["[0.03, 0.1)"][0] == 0.125 and np.isclose(rows["[0.03, 0.1)"][3], 1.0, rtol=1e-4)
    assert rows["[0.1, inf)"][0] == 0.5 and np.isclose(rows["[0.1, inf)"][3], 2.0, rtol=1e-4)
    assert "all: ratio 1.500" in out


def test_demod_probe_box_keeps_constants_and_restores_texture_under_smooth_light() -> None:
    """Catches a box filter that is not a mean (a constant image changes, or the edge is padded with zeros) and a
    demodulation that is not inverted exactly: where the light is smooth and only the albedo has detail, the
    demodulated box gives the image back, while the plain box smears the texture."""
    dp = load_script("demod_probe")
    c = np.full((3, 6, 7), 2.5)
    assert np.allclose(dp.box(c, 2), c)
    albedo = 0.2 + 0.6 * (np.indices((6, 7)).sum(axis=0) % 2)[None].repeat(3, axis=0)
    light = np.linspace(1.0, 2.0, 7)[None, None, :].repeat(6, axis=1).repeat(3, axis=0)
    y = albedo * light
    demod = albedo * dp.box(y / albedo, 1)
    assert dp.pixel_relmse(demod, y).mean() < 1e-3 < dp.pixel_relmse(dp.box(y, 1), y).mean()


def test_bias_variance_split_is_unbiased_and_sample_sets_are_disjoint() -> None:
    """Catches a variance taken with 1/n instead of 1/(n - 1), or a bias that keeps the mean's own
    variance (s^2 / n): over many draws of outputs y_j = r + b + noise, the bias part must average
    to w b^2 and the variance part to w sigma^2 (each within 3 standard errors, measured here). Also
    catches sample sets that overlap: set j must read stored samples j*k .. j*k + k - 1."""
    bv = load_script("bias_variance_probe")
    rng = np.random.default_rng(0)
    ref = np.full((3, 8, 8), 2.0)
    b, sigma, n = 0.3, 0.5, 4
    w = 1 / (4.0 + 0.01)
    parts = np.array([bv.split(ref + b + sigma * rng.standard_normal((n, 3, 8, 8)), ref) for _ in range(400)])
    se = parts.std(axis=0) / np.sqrt(len(parts))
    assert abs(parts[:, 1].mean() - w * b * b) < 3 * se[1] + 1e-12
    assert abs(parts[:, 2].mean() - w * sigma * sigma) < 3 * se[2] + 1e-12
    assert np.allclose(parts[:, 0], parts[:, 1] + parts[:, 2])

    class Reader:
        def read(self, names, *, samples=None, crop=None):
            return {"radiance": np.array(samples)}

    class Folder:
        samples = Reader()
        path = "x"

    s = bv.SampleSet(Folder(), 8)
    assert s.samples.read(["radiance"], samples=[0, 1, 2, 3])["radiance"].tolist() == [8, 9, 10, 11]
    assert s.path == "x"


def test_bias_variance_luminance_shares_add_up_and_follow_the_reference() -> None:
    """Catches luminance bins that lose or double-count pixels (shares must add up to split's parts),
    shares divided by the bin's pixel count instead of the image's, and a pixel put in the wrong
    decade: a bias placed only where the reference is 0.05 must land in the 0.01-0.1 bin alone."""
    bv = load_script("bias_variance_probe")
    rng = np.random.default_rng(1)
    ref = np.exp(rng.uniform(np.log(1e-3), np.log(50.0), (1, 16, 16))).repeat(3, axis=0)
    outs = ref + 0.2 * ref * rng.standard_normal((4, 3, 16, 16))
    total, bias, var = bv.split(outs, ref)
    shares = bv.by_luminance(*bv.split_maps(outs, ref), ref)
    assert shares.shape == (len(bv.LUMINANCE_EDGES) - 1, 3)
    assert np.isclose(shares[:, 0].sum(), 1.0)
    assert np.isclose(shares[:, 1].sum(), bias) and np.isclose(shares[:, 2].sum(), var)
    ref2 = np.full((3, 4, 4), 5.0)
    ref2[:, 0, 0] = 0.05
    outs2 = np.repeat(ref2[None], 4, axis=0)
    outs2[:, :, 0, 0] += 0.1  # the same offset in every set: bias only
    s2 = bv.by_luminance(*bv.split_maps(outs2, ref2), ref2)
    assert np.allclose(s2[:, 0], [0, 1 / 16, 0, 15 / 16, 0])
    w = 1 / (0.05**2 + bv.EPS)
    assert np.allclose(s2[:, 1], [0, w * 0.01 / 16, 0, 0, 0]) and np.allclose(s2[:, 2], 0)


def test_bias_variance_spread_scale_reaches_the_head_features(monkeypatch) -> None:
    """Catches a --spread-scale that patches a copy the head never calls (refine_features looks the
    function up in its module) or scales the halves' mean along with their difference: with K = 3
    the features equal those of halves three times as far apart about the same mean, and K = 0
    gives what agreeing halves give."""
    import torch

    from mcdenoise.models import refine

    bv = load_script("bias_variance_probe")
    monkeypatch.setattr(refine, "spread_features", refine.spread_features)  # undone after the test
    orig = refine.spread_features
    g = torch.Generator().manual_seed(0)
    lum, a, b = (torch.rand(1, 1, 8, 8, generator=g) + 0.1 for _ in range(3))
    mid = (a + b) / 2
    bv.scale_spread(3.0)
    assert torch.allclose(refine.spread_features(lum, a, b), orig(lum, mid + 3 * (a - mid), mid + 3 * (b - mid)))
    # Through the head's feature function, with halves close enough that the scaled ones stay >= 0.
    base, noisy, var, alb, nrm = (torch.rand(1, 3, 8, 8, generator=g) + 0.5 for _ in range(5))
    ha, hb = base + 0.05 * torch.rand(1, 3, 8, 8, generator=g), base - 0.05 * torch.rand(1, 3, 8, 8, generator=g)
    got = refine.refine_features(base, noisy, var, alb, nrm, None, halves=(ha, hb))
    monkeypatch.setattr(refine, "spread_features", orig)
    m3 = (ha + hb) / 2
    want = refine.refine_features(base, noisy, var, alb, nrm, None, halves=(m3 + 3 * (ha - m3), m3 + 3 * (hb - m3)))
    assert torch.allclose(got, want, atol=1e-6)
    bv.scale_spread(0.0)
    assert torch.allclose(refine.spread_features(lum, a, b), orig(lum, mid, mid))
    assert float(refine.spread_features(lum, a, b).abs().max()) < 1e-12


def test_kernel_noise_probe_modes_reduce_to_the_model_and_change_with_their_source() -> None:
    """Catches a probe whose re-assembled forward drifts from the layer model's own (exposure, lights,
    the consistency clamp or the kernels' inputs wired differently): with the set itself as the source
    of the kernels or of the context every mode is the model's output. And catches modes that ignore
    their source: another draw of the samples as the source must change the output."""
    from mcdenoise.models.registry import build_model, synthetic_batch

    kp = load_script("kernel_noise_probe")
    torch.manual_seed(0)
    model = build_model("layer", "small").double().eval()
    model.config.consistency = 4.0  # the shipped layer-medium's clamp: the probe must apply it as forward does
    b = synthetic_batch(model, spp=4, height=20, width=24, generator=torch.Generator().manual_seed(1))
    other = synthetic_batch(model, spp=4, height=20, width=24, generator=torch.Generator().manual_seed(2))
    b = {k: v.double() for k, v in b.items()}
    other = {k: v.double() for k, v in other.items()}
    other["radiance"] = b["radiance"] * (1 + 0.5 * torch.rand(b["radiance"].shape, generator=torch.Generator().manual_seed(3),
                                                                  dtype=torch.float64))
    with torch.no_grad():
        want = model(b)
        for kw in ({}, {"kernels_from": b}, {"context_from": b}, {"kernels_from": b, "context_from": b}):
            torch.testing.assert_close(kp.layer_output(model, b, **kw), want, rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(kp.layer_output(model, b, context_filter=lambda m: m), want, rtol=1e-10, atol=1e-12)
        for kw in ({"kernels_from": other}, {"context_from": other}, {"context_filter": kp.box_smooth}):
            assert float((kp.layer_output(model, b, **kw) - want).abs().max()) > 1e-6


def test_kernel_noise_probe_guided_smooth_keeps_constants_and_edges() -> None:
    """Catches unnormalised weights (a constant embedding would change) and weights that ignore the
    guide (a step in the guide, e.g. an object's silhouette, would be smoothed across)."""
    kp = load_script("kernel_noise_probe")
    g = torch.Generator().manual_seed(0)
    guide = torch.rand(1, 6, 9, 10, generator=g, dtype=torch.float64)
    const = torch.full((1, 4, 9, 10), 2.5, dtype=torch.float64)
    torch.testing.assert_close(kp.guided_smooth(const, guide), const)
    torch.testing.assert_close(kp.box_smooth(const), const)
    step = torch.zeros(1, 1, 9, 10, dtype=torch.float64)
    step[..., 5:] = 1.0
    x = step.expand(1, 3, 9, 10) + 0.01 * torch.randn(1, 3, 9, 10, generator=g, dtype=torch.float64)
    out = kp.guided_smooth(x, step.expand(1, 6, 9, 10) * 5)  # a guide step of 5, 50 sigma
    assert float((out - step).abs().max()) < 0.05  # each side keeps its own level
    assert float((kp.box_smooth(x) - step).abs().max()) > 0.3  # the plain box crosses the step


def test_kernel_noise_probe_shifted_samples_keep_their_spread_about_the_new_mean() -> None:
    """Catches a shift that rescales the samples (the context would read another noise level) or
    misses the new mean."""
    kp = load_script("kernel_noise_probe")
    g = torch.Generator().manual_seed(0)
    rad = torch.rand(2, 5, 3, 4, 6, generator=g, dtype=torch.float64)
    mean = torch.rand(2, 3, 4, 6, generator=g, dtype=torch.float64)
    out = kp.shifted_samples(rad, mean)
    torch.testing.assert_close(out.mean(dim=1), mean)
    torch.testing.assert_close(out - out.mean(dim=1, keepdim=True), rad - rad.mean(dim=1, keepdim=True))
