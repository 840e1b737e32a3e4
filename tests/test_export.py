"""`mcdenoise export`: the exported file runs outside the model's Python code and matches PyTorch
(issue 11, item 3)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from mcdenoise.cli.main import main
from mcdenoise.infer.export import input_names
from mcdenoise.models import build_model, synthetic_batch


def _weights(tmp_path, name: str):
    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    path = tmp_path / f"{name}.safetensors"
    save_file(model.state_dict(), str(path), metadata={"model": name, "preset": "small"})
    return model, str(path)


def _sample_input(model, size, spp):
    batch = synthetic_batch(model, spp=spp, height=size[0], width=size[1], generator=torch.Generator().manual_seed(7))
    return batch, [batch[n] for n in input_names(model)]


def test_torchscript_runs_and_matches(tmp_path, capfd):
    """Catches an exported TorchScript file that loads but computes something else (or depends on
    the mcdenoise Python code at run time: it is loaded with torch.jit only)."""
    model, weights = _weights(tmp_path, "wskp")
    out = tmp_path / "wskp.pt"
    rc = main(["export", "--model", weights, "--format", "torchscript", "-o", str(out), "--size", "48x40"])
    assert rc == 0, capfd.readouterr().err
    desc = json.loads((tmp_path / "wskp.pt.json").read_text())
    assert [i["name"] for i in desc["inputs"]] == input_names(model)
    size = (48, 40) if not desc["any_size"] else (37, 29)
    batch, args = _sample_input(model, size, 1)
    loaded = torch.jit.load(str(out))
    with torch.no_grad():
        got, want = loaded(*args), model(batch)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


def test_onnx_runs_in_onnxruntime_and_matches(tmp_path, capfd):
    """Catches an ONNX file onnxruntime rejects, or whose inputs are not in the documented order."""
    ort = pytest.importorskip("onnxruntime")
    model, weights = _weights(tmp_path, "wskp")
    out = tmp_path / "wskp.onnx"
    rc = main(["export", "--model", weights, "--format", "onnx", "-o", str(out), "--size", "32x32"])
    assert rc == 0, capfd.readouterr().err
    desc = json.loads((tmp_path / "wskp.onnx.json").read_text())
    batch, args = _sample_input(model, (32, 32), 1)
    sess = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == [i["name"] for i in desc["inputs"]]
    got = sess.run(None, {i.name: a.numpy() for i, a in zip(sess.get_inputs(), args)})[0]
    with torch.no_grad():
        want = model(batch).numpy()
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


def test_unexportable_model_is_refused_in_one_line(tmp_path, capfd):
    """Catches an export failure surfacing as a traceback (or a file left behind)."""
    _, weights = _weights(tmp_path, "pixel_gather")
    out = tmp_path / "pg.pt"
    rc = main(["export", "--model", weights, "--format", "torchscript", "-o", str(out), "--size", "16x16"])
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert rc == 1 and len(err) == 1 and "cannot be exported" in err[0], err
    assert not out.exists()


def _works_or_refuses(model, path, fmt, size, spp) -> str:
    """"ok" when the exported file matches PyTorch at ``size``/``spp``, "refused" when it raises;
    fails the test when it returns anything else (a silently wrong result)."""
    from mcdenoise.infer.export import run_exported

    batch, args = _sample_input(model, size, spp)
    try:
        got = run_exported(path, fmt, tuple(args))
    except Exception:  # torch.jit / onnxruntime raise their own types
        return "refused"
    with torch.no_grad():
        want = model(batch)
    assert got.shape == want.shape, (size, spp)
    err = float((got - want).abs().max() / want.abs().max())
    assert err <= 1e-4, f"{type(model).__name__} {fmt} at {size} {spp} spp: silently wrong (relative error {err:.2f})"
    return "ok"


def _exportable() -> list[str]:
    from mcdenoise.models import list_models

    return sorted(e.name for e in list_models())


@pytest.mark.parametrize("name", _exportable())
def test_torchscript_works_or_refuses_at_every_size_and_spp(name, tmp_path):
    """Catches issue 22 item 6: `export --model layer --format torchscript --size 32x32 --spp 4` ran
    at 8 spp with relative error 0.60 and no refusal. For every model that exports, the file
    matches PyTorch at each size and spp it accepts and raises at the others; its JSON declares
    the fixed H, W (and S) when it is not any-size."""
    from mcdenoise.infer.export import ExportError, export_model

    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    out = tmp_path / f"{name}.pt"
    try:
        desc = export_model(model, out, "torchscript", example_size=(32, 32), spp=4)
    except ExportError as e:
        assert "cannot be exported" in str(e) and "\n" not in str(e)
        assert not out.exists()
        return
    sample = model.input_kind == "samples"
    assert _works_or_refuses(model, out, "torchscript", (32, 32), 4) == "ok"
    results = [_works_or_refuses(model, out, "torchscript", size, spp)
               for size, spp in (((32, 32), 8), ((32, 32), 2), ((40, 36), 4), ((19, 23), 3))]
    if desc["any_size"]:
        assert results == ["ok"] * 4
    else:
        assert "refused" in results
        shape = desc["inputs"][0]["shape"]
        assert shape[-2:] == ["32", "32"] and (not sample or shape[1] == "4"), shape


def test_onnx_json_declares_the_fixed_size(tmp_path, capfd):
    """Catches issue 22 item 6's ONNX half: the file refused other sizes but its JSON declared
    symbolic H, W."""
    pytest.importorskip("onnxruntime")
    model, weights = _weights(tmp_path, "wskp")
    out = tmp_path / "w.onnx"
    assert main(["export", "--model", weights, "--format", "onnx", "-o", str(out), "--size", "24x20"]) == 0, \
        capfd.readouterr().err
    desc = json.loads((tmp_path / "w.onnx.json").read_text())
    assert _works_or_refuses(model, out, "onnx", (24, 20), 1) == "ok"
    if not desc["any_size"]:
        assert _works_or_refuses(model, out, "onnx", (30, 22), 1) == "refused"
        assert all(i["shape"][-2:] == ["24", "20"] for i in desc["inputs"]), desc["inputs"]
        assert desc["output"]["shape"] == ["1", "3", "24", "20"]
