"""ConvTranspose(4, s2, p1) -> phase Convs + DepthToSpace rewrite: exact in fp32, dynamic N kept."""

from __future__ import annotations

import onnxruntime as ort
import pytest
import torch

from msfnet.export.onnx_export import random_inputs
from msfnet.export.passes import PASSES, PassContext
from msfnet.export.rewrite import rewrite_deconvs
from msfnet.export.variants import ExportOptions, get_variant
from msfnet.model.network import MSFNet
from msfnet.runtime.evaluate.metrics import angular_error_deg


@pytest.fixture(scope="module")
def fp32_model(tmp_path_factory):
    """The fp32 graph as msf-export's torch-export pass makes it (opset 17, dynamic axes): what
    the int8 variants' rewrite-deconvs pass gets (metadata aside), unverified and in memory."""
    torch.manual_seed(0)
    net = MSFNet().eval()
    folder = tmp_path_factory.mktemp("rw")
    ctx = PassContext(
        net, get_variant("fp32"), ExportOptions(), folder / "unused.pth", folder / "unused.onnx"
    )
    return net, PASSES["torch-export"].run(None, ctx)


def test_rewritten_graph_matches_pytorch(fp32_model):
    net, proto = fp32_model
    model, count = rewrite_deconvs(proto)
    assert count == 3
    assert not any(n.op_type == "ConvTranspose" for n in model.graph.node)
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    for n, h, w in ((3, 16, 20), (9, 24, 16)):  # two light counts: N stays dynamic
        images, lights = random_inputs(1, n, h, w, seed=n)
        (out,) = sess.run(["normals"], {"images": images, "lights": lights})
        with torch.no_grad():
            ref = net(torch.from_numpy(images), torch.from_numpy(lights)).numpy()
        d = angular_error_deg(out[0].transpose(1, 2, 0), ref[0].transpose(1, 2, 0))
        assert d.max() < 0.01
