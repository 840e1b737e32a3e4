"""`mcdenoise eval` (mcdenoise/eval/runner.py, html.py, resultsmd.py, cli/eval.py) on tiny data.

Two randomly initialised small models (a pixel model and a sample model) saved as safetensors
stand in for trained weights; the numbers are meaningless, the report's consistency is not.
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from mcdenoise.cli.main import main
from mcdenoise.data.dataset import Dataset, read_manifest, write_manifest
from mcdenoise.data.format import pixel_stats
from mcdenoise.data.tensors import input_arrays
from mcdenoise.eval import EvalError, evaluate
from mcdenoise.eval.metrics import METRICS
from mcdenoise.eval.oidn import oidn_available
from mcdenoise.models.registry import build_model
from repo_scripts import load_script
from train_tiny_data import make_tiny_dataset

SPP = (2, 4, 8, 16)  # the tiny images store 8: 16 must be skipped with a note
MODELS = ("wskp", "layer")  # one pixel model, one sample model, both cheap


def _save_model(path: Path, name: str) -> Path:
    from safetensors.torch import save_file

    torch.manual_seed(0)
    m = build_model(name, "small")
    save_file({k: v.contiguous() for k, v in m.state_dict().items()}, str(path), metadata={"model": name, "preset": "small"})
    return path


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three 24x24 test images (8 spp, references); the second is flagged depth of field."""
    root = make_tiny_dataset(tmp_path_factory.mktemp("evaldata"), train=1, val=3, spp=8, size=24)
    entries = [{**e, "split": "test" if e["split"] == "val" else e["split"]} for e in read_manifest(root)]
    write_manifest(root, entries)
    meta = root / entries[2]["path"] / "meta.json"
    doc = json.loads(meta.read_text())
    doc["extra"]["procedural"] = {"depth_of_field": True, "motion_blur": False}
    from mcdenoise.data.meta import seal_meta

    meta.write_text(json.dumps(seal_meta(doc)))  # meta.json carries its own checksum (issue 22)
    return root


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    d = tmp_path_factory.mktemp("evalmodels")
    return [_save_model(d / f"{n}_rand.safetensors", n) for n in MODELS]


@pytest.fixture(scope="module")
def report(data: Path, models: list[Path], tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, Path]:
    out = tmp_path_factory.mktemp("evalout") / "report"
    md = out.parent / "RESULTS.md"
    md.write_text("# Results\n\nHand-written prose.\n")
    doc = evaluate(models=[str(m) for m in models], data=[data], out=out, spp=SPP, threads=1, progress=False,
                   results_md=md, section="tiny")
    return out, doc, md


def test_input_arrays_first_k_samples(data: Path) -> None:
    """Catches eval and validation disagreeing on what "k samples" means: pixel inputs are the
    mean/variance of samples 0..k-1, all samples read noisy.exr, sample inputs are samples 0..k-1."""
    im = Dataset(data).images("test")[0]
    smp = im.samples.read(["radiance"])["radiance"]
    a = input_arrays(im, ["radiance", "radiance_variance"], "pixels", spp=3)
    mean, var = pixel_stats(smp[:3])
    np.testing.assert_array_equal(a["radiance"], mean)
    np.testing.assert_array_equal(a["radiance_variance"], var)
    full = input_arrays(im, ["radiance"], "pixels")
    np.testing.assert_allclose(full["radiance"], pixel_stats(smp)[0], rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(input_arrays(im, ["radiance"], "samples", spp=2)["radiance"], smp[:2])
    with pytest.raises(ValueError, match="stores 8"):
        input_arrays(im, ["radiance"], "pixels", spp=9)


def test_results_json_rows_and_summary(report: tuple[Path, dict, Path]) -> None:
    """Catches a method or spp missing from the rows, a mean that is not the mean of its rows,
    and a model label replaced by its registered name."""
    out, doc, _ = report
    on_disk = json.loads((out / "results.json").read_text())
    assert on_disk == doc
    names = [m["name"] for m in doc["methods"]]
    expect = ["noisy", *(["oidn-high", "oidn-fast"] if oidn_available() else []), "nlmeans", "wskp_rand", "layer_rand"]
    assert names == expect
    assert [m["model"] for m in doc["methods"] if m["kind"] == "model"] == list(MODELS)
    assert all(Path(m["weights"]).is_file() for m in doc["methods"] if m["kind"] == "model")
    images = [im["id"] for im in doc["images"]]
    assert len(images) == 3
    ks = (2, 4, 8)
    assert len(doc["rows"]) == len(images) * len(ks) * len(names)
    assert {(r["image"], r["spp"], r["method"]) for r in doc["rows"]} == {(i, k, n) for i in images for k in ks for n in names}
    assert sum("16 spp skipped" in n for n in doc["notes"]) == 3
    for r in doc["rows"]:
        assert set(METRICS) <= set(r)
        assert (r["seconds"] is None) == (r["method"] == "noisy")
    dof = [im["id"] for im in doc["images"] if im["effects"]]
    assert dof == [images[1]]
    for s in doc["summary"]:
        sel = [r for r in doc["rows"] if r["method"] == s["method"] and r["spp"] == s["spp"]
               and (s["subset"] == "all" or r["image"] in dof)]
        assert s["images"] == len(sel) == (3 if s["subset"] == "all" else 1)
        assert s["relmse"] == pytest.approx(np.mean([r["relmse"] for r in sel]), rel=1e-12)
    p = doc["provenance"]
    assert p["torch"] == torch.__version__ and p["mcdenoise"] and p["machine"]
    assert ("oidn" in p) == oidn_available()


def test_noisy_relmse_falls_with_spp(report: tuple[Path, dict, Path]) -> None:
    """Catches inputs that ignore k (e.g. always all stored samples, or always the first one)."""
    _, doc, _ = report
    noisy = {s["spp"]: s["relmse"] for s in doc["summary"] if s["method"] == "noisy" and s["subset"] == "all"}
    assert noisy[2] > noisy[4] > noisy[8]


def test_denoisers_beat_noisy(report: tuple[Path, dict, Path]) -> None:
    """Catches OIDN or NL-means fed the wrong buffers (e.g. albedo as colour, clamped LDR)."""
    _, doc, _ = report
    mean = {(s["method"], s["spp"]): s["relmse"] for s in doc["summary"] if s["subset"] == "all"}
    for k in (2, 4, 8):
        # Two samples give NL-means a poor variance estimate (0.6x of noisy at 2 spp, 0.45x at 4).
        assert mean[("nlmeans", k)] < (0.8 if k == 2 else 0.5) * mean[("noisy", k)]
        if oidn_available():
            assert mean[("oidn-high", k)] < 0.5 * mean[("noisy", k)]


def test_csv_numbers_equal_json(report: tuple[Path, dict, Path]) -> None:
    """Catches the CSV rounding numbers or reordering columns relative to results.json."""
    out, doc, _ = report
    with open(out / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(doc["rows"])
    for c, j in zip(rows, doc["rows"]):
        assert (c["image"], int(c["spp"]), c["method"]) == (j["image"], j["spp"], j["method"])
        for key, v in j.items():
            if key in ("image", "spp", "method"):
                continue
            assert (c[key] == "") if v is None else float(c[key]) == v, (key, c[key], v)


def test_html_references_existing_images(report: tuple[Path, dict, Path]) -> None:
    """Catches a page pointing at PNGs that were not written (or written elsewhere), and a page
    that fetches anything from the network or runs scripts."""
    out, doc, _ = report
    page = (out / "index.html").read_text()
    srcs = re.findall(r"<img[^>]*\ssrc='([^']+)'", page)
    n_methods = len(doc["methods"])
    # per image and spp: an image + error map per method, plus the reference; the plot and legend.
    assert len(srcs) == 3 * 3 * (2 * n_methods + 1) + 2
    for s in srcs:
        assert not re.match(r"[a-z]+:", s), s
        f = out / s
        assert f.is_file() and f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", s
    assert "<script" not in page and "http" not in page
    for m in doc["methods"]:
        assert f">{m['name']}<" in page or f">{m['name']}<br>" in page


def test_results_md_block(report: tuple[Path, dict, Path]) -> None:
    """Catches the block overwriting the prose around it, or missing the ratios, floors and the
    depth-of-field / motion-blur table."""
    _, doc, md = report
    text = md.read_text()
    assert text.startswith("# Results\n\nHand-written prose.\n")
    assert "<!-- BEGIN generated:eval:tiny -->" in text and "<!-- END generated:eval:tiny -->" in text
    assert doc["command"] in text
    for name in ("wskp_rand", "layer_rand"):
        assert re.search(rf"- {name}: floor \(>= 10x over noisy at 8 spp\): (met|missed) \(", text)
        assert re.search(rf"\| {name} \| 4 \| [0-9.e+-]+ \| [0-9.e+-]+ \| ", text)
    assert "Depth-of-field / motion-blur images only (1)" in text
    # Bug caught (issue 18 section 2): ms/MP without the thread counts and precision behind it.
    oidn = ", OIDN 1 thread(s)" if oidn_available() else ""
    assert f"per megapixel, torch 1 thread(s){oidn}, models in float32." in text


def test_cli_writes_report_and_replaces_it(data: Path, models: list[Path], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """Catches the CLI wiring (flags to evaluate) and a second run refusing its own earlier report."""
    out = tmp_path / "rep"
    argv = ["eval", "--models", str(models[0]), "--data", str(data), "--spp", "4", "--out", str(out),
            "--no-oidn", "--no-html", "--no-progress", "--threads", "1", "--max-images", "2"]
    assert main(argv) == 0
    assert main(argv) == 0
    doc = json.loads((out / "results.json").read_text())
    assert [m["name"] for m in doc["methods"]] == ["noisy", "nlmeans", "wskp_rand"]
    assert len(doc["rows"]) == 2 * 3 and not (out / "index.html").exists()
    assert doc["command"].startswith("mcdenoise eval --models ") and "--no-oidn" in doc["command"]
    assert "2 images" in capsys.readouterr().err


def test_cli_save_images_feed_blend_outputs(data: Path, models: list[Path], tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    """Catches --save-images not reaching evaluate (no EXRs), saved outputs that differ from the scored
    ones, and scripts/blend_outputs.py mixing up members, weights or its median."""
    from mcdenoise.eval.scores import image_metrics
    from mcdenoise.io.exr import read_exr

    out = tmp_path / "rep"
    assert main(["eval", "--models", *map(str, models), "--data", str(data), "--spp", "4", "--out", str(out), "--no-oidn",
                 "--no-classic", "--no-html", "--no-progress", "--threads", "1", "--max-images", "1",
                 "--save-images"]) == 0
    doc = json.loads((out / "results.json").read_text())
    assert "--save-images" in doc["command"]
    row = next(r for r in doc["rows"] if r["method"] == "wskp_rand")
    folder = out / "images" / row["image"]
    ref = read_exr(folder / "reference.exr")["radiance"]
    outs = {m: read_exr(folder / "4spp" / f"{m}.exr")["radiance"] for m in ("noisy", "wskp_rand", "layer_rand")}
    assert image_metrics(outs["wskp_rand"], ref, ["relmse"])["relmse"] == pytest.approx(row["relmse"], rel=1e-6)

    blend = load_script("blend_outputs")
    a, b, n = outs["wskp_rand"], outs["layer_rand"], outs["noisy"]
    np.testing.assert_allclose(blend.apply_blend(blend.parse_blend("x=wskp_rand+layer_rand"), outs), (a + b) / 2, rtol=1e-6)
    np.testing.assert_allclose(blend.apply_blend(blend.parse_blend("x=0.25*wskp_rand+0.75*layer_rand"), outs),
                               0.25 * a + 0.75 * b, rtol=1e-6)
    med = blend.apply_blend(blend.parse_blend("x=median:wskp_rand+layer_rand+noisy"), outs)
    np.testing.assert_allclose(med, np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), n)), rtol=1e-6)
    for bad in ("x=wskp_rand", "x=0.5*a+0.6*b", "noequals"):
        with pytest.raises(ValueError):
            blend.parse_blend(bad)


def _one_line_error(argv: list[str], capsys: pytest.CaptureFixture[str], pattern: str) -> None:
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(pattern, err), err


def test_cli_errors_are_one_line(data: Path, models: list[Path], tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Catches tracebacks (or silent empty reports) for the mistakes users make."""
    base = ["eval", "--data", str(data), "--out", str(tmp_path / "r"), "--no-progress", "--no-oidn"]
    _one_line_error([*base, "--models", "no_such_model"], capsys, r"^mcdenoise eval: error: no_such_model: neither")
    _one_line_error([*base, "--split", "val"], capsys, r"no images in the 'val' split \(train 1, val 0, test 3\)")
    _one_line_error([*base, "--split", "valid"], capsys, r"unknown split 'valid'")
    _one_line_error([*base, "--spp"], capsys, r"no sample counts given")
    _one_line_error([*base, "--spp", "0", "4"], capsys, r"sample counts must be at least 1")
    _one_line_error([*base, "--results-md", str(tmp_path / "R.md")], capsys, r"go together")
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    _one_line_error([*base[:3], "--out", str(other), "--no-progress"], capsys, r"not an earlier report")
    assert (other / "keep.txt").is_file()
    _one_line_error(["eval", "--data", str(tmp_path / "nothing"), "--out", str(tmp_path / "r")], capsys,
                    r"nothing: no such folder")


def test_data_without_references_is_refused(data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Catches images without a reference being scored against nothing (or against themselves)."""
    import shutil

    img = tmp_path / "noref"
    shutil.copytree(data / read_manifest(data)[1]["path"], img)
    meta = json.loads((img / "meta.json").read_text())
    del meta["files"]["reference"]
    from mcdenoise.data.meta import seal_meta

    (img / "meta.json").write_text(json.dumps(seal_meta(meta)))  # an intact meta.json without a reference
    (img / "reference.exr").unlink()
    _one_line_error(["eval", "--data", str(img), "--out", str(tmp_path / "r"), "--no-progress"], capsys,
                    r"none of its 1 image\(s\) has a reference")
    with pytest.raises(EvalError, match="has a reference"):
        evaluate(data=img, out=tmp_path / "r2", progress=False)


def test_image_folder_and_folder_of_images(data: Path, tmp_path: Path) -> None:
    """Catches `mcdenoise render` outputs (one image folder, or a folder of them) not being accepted."""
    import shutil

    scenes = tmp_path / "scenes"
    for e in read_manifest(data)[1:3]:
        shutil.copytree(data / e["path"], scenes / Path(e["path"]).name)
    doc = evaluate(data=[scenes / "002", scenes], out=tmp_path / "r", spp=[8], oidn=[], classic=False,
                   html=False, progress=False)
    assert [im["id"] for im in doc["images"]] == ["002", "scenes/001", "scenes/002"]
    assert [im["effects"] for im in doc["images"]] == [["depth_of_field"], [], ["depth_of_field"]]


def test_spp_above_the_stored_count_is_refused(data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Catches issue 22 item 10: `eval --spp 64` on 8-spp data exited 0 with an empty report; it
    must be one line naming the stored spp, and write no report."""
    _one_line_error(["eval", "--data", str(data), "--spp", "64", "--out", str(tmp_path / "r"), "--no-progress"], capsys,
                    r"--spp 64: .*stores 8 spp")
    assert not (tmp_path / "r").exists()


def test_page_and_terminal_lead_with_the_ranked_summary(report: tuple[Path, dict, Path], data: Path,
                                                        models: list[Path], tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """Bugs caught (issue 18 section 3): the page opened on an 11-column table with no ranking,
    nothing highlighted and no ratio to OIDN; its title was "mcdenoise eval" whatever the data;
    crop rows were inline figures whose spp label ("4 spp" vs "16 spp") shifted each row against
    the others; `mcdenoise eval` printed only a path."""
    from mcdenoise.eval.ranking import ranked

    out, doc, _ = report
    page = (out / "index.html").read_text()
    assert f"<title>{data.name} (test split): 3 image(s) at 2, 4, 8 spp" in page
    assert page.index("<table class='rank'>") < page.index("Every metric, means over all images")
    for t in ranked(doc):
        vals = [r["relmse"] for r in t["rows"]]
        assert vals == sorted(vals)  # best first
        assert t["rows"][0]["best"] >= {"relmse"}
        if oidn_available():
            assert t["columns"][-1][0] == "vs_oidn"
            assert next(r for r in t["rows"] if r["method"] == "oidn-high")["vs_oidn"] == 1.0
    first = page[page.index("<table class='rank'>"):page.index("</table>")]
    best = ranked(doc)[0]["rows"][0]
    assert f"<td class='name'>{best['method']}</td><td><b>" in first  # the best relMSE in bold
    assert "x OIDN high" in first or not oidn_available()
    assert "torch 1 thread(s)" in page
    # The crops: one table per image, every row the same cells (method columns + reference).
    tables = re.findall(r"<table class='crops'>(.*?)</table>", page, re.S)
    assert len(tables) == 3 and "<figure>" not in page
    for tb in tables:
        rows = re.findall(r"<tr>(.*?)</tr>", tb, re.S)
        assert len(rows) == 4  # header + 3 spp
        assert len({r.count("<td") + r.count("<th") for r in rows}) == 1

    argv = ["eval", "--models", str(models[0]), "--data", str(data), "--spp", "4", "--out", str(tmp_path / "r"),
            "--no-oidn", "--no-html", "--no-progress", "--threads", "1", "--max-images", "2"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "4 spp, mean over 2 image(s), best relMSE first" in text
    one = tmp_path / "one"  # an image folder (the demo's render): no split in the title
    import shutil

    shutil.copytree(data / read_manifest(data)[1]["path"], one)
    evaluate(data=[one], out=tmp_path / "r1", spp=[4], oidn=[], classic=False, progress=False)
    assert "<title>one: 1 image(s) at 4 spp" in (tmp_path / "r1" / "index.html").read_text()
    lines = [ln.split() for ln in text.splitlines() if re.match(r"\s+\d+\s", ln)]
    assert [ln[1] for ln in lines] and lines[-1][1] == "noisy"  # noisy ranks last here
    assert "torch 1 thread(s)" in text


def test_all_dof_images_do_not_repeat_the_tables(report: tuple[Path, dict, Path], tmp_path: Path) -> None:
    """Bug caught (issue 18): when every image has depth of field (the demo), the page and the
    Markdown block repeated the main tables under "depth-of-field / motion-blur"."""
    from mcdenoise.eval import html as page_mod
    from mcdenoise.eval.ranking import same_images
    from mcdenoise.eval.resultsmd import render_block

    _, doc, _ = report
    assert not same_images(doc)
    all_dof = {**doc, "summary": [s for s in doc["summary"] if s["subset"] == "all"]
               + [{**s, "subset": "dof_motion"} for s in doc["summary"] if s["subset"] == "all"]}
    assert same_images(all_dof)
    page = page_mod.write_report(tmp_path, all_dof, page_mod.CropWriter(tmp_path)).read_text()
    assert "All 3 images have depth of field or motion blur." in page
    assert "depth-of-field / motion-blur images</h" not in page.lower() and page.count("<table class='rank'>") == 3
    md = render_block(all_dof)
    assert "Depth-of-field / motion-blur images only" not in md and "All 3 images have depth of field" in md
    # A real subset keeps its own tables.
    page = page_mod.write_report(tmp_path, doc, page_mod.CropWriter(tmp_path)).read_text()
    assert "<h3>Depth-of-field / motion-blur images</h3>" in page and page.count("<table class='rank'>") == 6


def test_run_folder_with_a_taken_label_keeps_its_path(data: Path, models: list[Path], tmp_path: Path) -> None:
    """Bug caught (issue 18): a run folder or weights file whose name is a shipped model's
    (`runs/layer` beside `layer`) was relabelled `layer-2` without a word; its label is now the
    path as given, and a note says so."""
    import shutil

    from mcdenoise.models.weights import shipped

    if not any(s.name == "wskp" and s.preset == "small" for s in shipped()):
        pytest.skip("no shipped wskp weights")
    mine = tmp_path / "runs" / "wskp.safetensors"
    mine.parent.mkdir()
    shutil.copyfile(models[0], mine)
    doc = evaluate(models=["wskp", str(mine)], data=[data], out=tmp_path / "r", spp=[4], oidn=[], classic=False,
                   max_images=1, html=False, progress=False)
    assert [m["name"] for m in doc["methods"]] == ["noisy", "wskp", str(mine)]
    assert any(n.startswith(f"{mine}: labelled") and "'wskp' was taken" in n for n in doc["notes"])


@pytest.mark.skipif(not oidn_available(), reason="pyoidn (OIDN 2.5.1) not installed")
def test_threads_reach_oidn(report: tuple[Path, dict, Path]) -> None:
    """Bug caught (issue 18 section 2): `eval --threads 1` gave torch one thread and OIDN every
    core; both must get the count, and results.json and the tables must say what each had."""
    _, doc, _ = report
    assert doc["config"]["threads"] == 1 and doc["config"]["oidn_threads"] == 1
    assert {m["threads"] for m in doc["methods"] if m["kind"] == "oidn"} == {1}
    from mcdenoise.eval.ranking import timing_note

    assert "torch 1 thread(s), OIDN 1 thread(s)" in timing_note(doc)


def test_overloaded_machine_is_warned_about_under_the_tables(data: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Bug caught (issue 18): times taken while the load average exceeded the core count (a
    render in the background) were reported like any other; a note and the line under the
    ranked tables now say so."""
    import os

    from mcdenoise.eval.ranking import summary_text

    monkeypatch.setattr(os, "getloadavg", lambda: (99.0, 99.0, 99.0))
    doc = evaluate(data=[data], out=tmp_path / "r", spp=[4], oidn=[], classic=True, max_images=1, html=False,
                   progress=False)
    assert sum(n.startswith("timing: load average 99.00") for n in doc["notes"]) == 2  # at start and at end
    assert "Warning: load average 99.00 at start exceeds" in summary_text(doc)
    monkeypatch.setattr(os, "getloadavg", lambda: (0.0, 0.0, 0.0))
    doc = evaluate(data=[data], out=tmp_path / "r", spp=[4], oidn=[], classic=True, max_images=1, html=False,
                   progress=False)
    assert not any(n.startswith("timing:") for n in doc["notes"]) and "Warning" not in summary_text(doc)


def test_small_evaluations_list_every_image(report: tuple[Path, dict, Path]) -> None:
    """Bug caught (issue 19): the validation block gave only means, hiding the scenes where a model
    is worse than the noisy input; a per-image table and that list are written for small sets."""
    from mcdenoise.eval.resultsmd import render_block

    _, doc, _ = report
    md = render_block(doc)
    k = doc["config"]["spp"][0]
    assert f"relMSE per image at {k} spp" in md
    rows = [ln for ln in md.splitlines() if ln.startswith("| ") and not ln.startswith("| spp") and not ln.startswith("| image")]
    assert len({r.split("|")[1].strip() for r in rows}) >= len(doc["images"])
    noisy = {(r["image"], r["spp"]): r["relmse"] for r in doc["rows"] if r["method"] == "noisy"}
    worse = [r for r in doc["rows"] if r["method"] != "noisy" and r["relmse"] > noisy[(r["image"], r["spp"])]]
    assert ("Worse than the noisy input" in md) == bool(worse)


def test_large_evaluations_still_say_where_a_model_is_worse_than_noisy(report: tuple[Path, dict, Path]) -> None:
    """Bug caught (campaign 23): an evaluation over several render seeds has too many images for
    per-image tables, and with them went the list of images where a model is worse than the noisy
    input, the check issue 19 asks for on every rendering. The list must name exactly the
    (method, image) pairs worse in relMSE or in PSNR, and say "none" where there are none."""
    import copy

    from mcdenoise.eval import resultsmd

    _, doc, _ = report
    big = copy.deepcopy(doc)
    big["images"] = big["images"] * (resultsmd.PER_IMAGE_MAX // len(doc["images"]) + 1)  # over the limit
    k = doc["config"]["spp"][0]
    model = next(m["name"] for m in doc["methods"] if m["name"] != "noisy")
    row = next(r for r in big["rows"] if r["method"] == model and r["spp"] == k)
    noisy = next(r for r in big["rows"] if r["method"] == "noisy" and r["spp"] == k and r["image"] == row["image"])
    for r in big["rows"]:  # every other method clearly better than noisy on every image...
        if r["method"] != "noisy":
            n = next(x for x in big["rows"] if x["method"] == "noisy" and x["spp"] == r["spp"] and x["image"] == r["image"])
            r["relmse"], r["psnr"] = n["relmse"] / 2, n["psnr"] + 1
    row["psnr"] = noisy["psnr"] - 0.01  # ...but one, worse in PSNR only
    md = resultsmd.render_block(big)
    lines = [ln for ln in md.splitlines() if ln.startswith("Worse than the noisy input in relMSE or PSNR")]
    assert len(lines) == len(doc["config"]["spp"])
    assert f"at {k} spp" in lines[0] and f"{model} on {Path(row['image']).name}." in lines[0]
    assert all(ln.endswith("none.") for ln in lines[1:])


def test_many_data_folders_are_counted_not_listed(report: tuple[Path, dict, Path]) -> None:
    """Bug caught (campaign 23): a six-seed evaluation of nine scenes listed 54 folder paths in its
    RESULTS.md block. Beyond the per-image limit they are counted per parent folder; below it every
    folder is still named."""
    import copy

    from mcdenoise.eval import resultsmd

    _, doc, _ = report
    assert all(f"`{d}`" in resultsmd.render_block(doc) for d in doc["config"]["data"])
    big = copy.deepcopy(doc)
    big["config"]["data"] = [f"work/scene{i}_seed{s}" for i in range(9) for s in range(2)]
    md = resultsmd.render_block(big)
    assert "18 folders in `work`" in md and "work/scene0_seed0" not in md
