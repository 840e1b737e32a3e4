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
