
import numpy as np
import pytest
import torch

from explorer.model import build_network, interpolate_scan, stage_specs
from explorer.space import SearchSpace, fastdepth_candidate, paper_candidate


def _forward(cand, h, w):
    net = build_network(cand).eval()
    with torch.no_grad():
        return net(torch.rand(2, 3, h, w), torch.rand(2, w) * 5 + 0.5)


@pytest.mark.parametrize("cand", list(SearchSpace.from_yaml("tiny").enumerate()))
def test_tiny_candidates_forward_square_and_not(cand):
    for h, w in ((32, 32), (32, 48)):
        outs = _forward(cand, h, w)
        assert len(outs) == cand.num_paths
        assert all(o.shape == (2, 1, h, w) for o in outs)


def test_default_space_sample_forward():
    for cand in SearchSpace.from_yaml("anytime_depth").random_candidates(3) + [paper_candidate()]:
        for h, w in ((64, 64), (64, 96)):
            outs = _forward(cand, h, w)
            assert len(outs) == cand.num_paths and all(o.shape == (2, 1, h, w) for o in outs)


@pytest.mark.parametrize("size", [(224, 224), (224, 320), (192, 640), (224, 896)])
def test_paper_sizes(size):
    outs = _forward(paper_candidate(), *size)
    assert [o.shape[-2:] for o in outs] == [torch.Size(size)] * 5


def test_fastdepth_baseline_is_one_exit_image_only():
    net = build_network(fastdepth_candidate())
    names = [s.name for s in net.specs]
    assert "lidar_encoder" not in names and names[-1] == "exit_5"
    assert 3.5e6 < sum(p.numel() for p in net.parameters()) < 4.5e6


def test_bad_inputs():
    net = build_network(paper_candidate())
    with pytest.raises(ValueError, match="divide"):
        net(torch.rand(1, 3, 100, 100), torch.rand(1, 100))
    with pytest.raises(ValueError, match="scan"):
        net(torch.rand(1, 3, 64, 64), torch.rand(1, 60))


def test_stages_are_ordered_prefixes():
    specs = stage_specs(paper_candidate())
    produced = {"image", "scan"}
    paths = []
    for s in specs:
        assert set(s.inputs) <= produced, s.name  # a stage only reads what ran before it
        produced |= set(s.outputs)
        if s.path is not None:
            paths.append(s.path)
    assert paths == [1, 2, 3, 4]


def test_path0_nearest_fill():
    scan = torch.tensor([[0.0, 2.0, 0.0, 0.0, 5.0, 0.0]])
    out = interpolate_scan(scan, 3)
    assert out.shape == (1, 1, 3, 6)
    assert out[0, 0, 0].tolist() == [2.0, 2.0, 2.0, 5.0, 5.0, 5.0]
    assert torch.equal(out[0, 0, 0], out[0, 0, 2])
    assert interpolate_scan(torch.zeros(1, 4), 2).abs().sum() == 0


def _nearest_by_search(scan: torch.Tensor) -> torch.Tensor:
    """Each column's nearest return by searching all columns (the first, so the left one, on a tie)."""
    n, w = scan.shape
    cols = torch.arange(w, dtype=scan.dtype)
    distance = (cols[:, None] - cols[None, :]).abs()[None] + (scan <= 0).to(scan.dtype)[:, None, :] * 4 * w
    return torch.gather(scan, 1, distance.argmin(dim=2))


def test_path0_takes_each_columns_nearest_return_as_a_search_of_all_columns_would():
    g = torch.Generator().manual_seed(0)
    for trial in range(300):
        n, w = int(torch.randint(1, 4, (1,), generator=g)), int(torch.randint(1, 40, (1,), generator=g))
        scan = torch.rand(n, w, generator=g) * 10
        scan[torch.rand(n, w, generator=g) < float(torch.rand(1, generator=g))] = 0.0   # gaps, up to none left
        if trial % 5 == 0:
            scan[:, ::2] = 0.0   # every gap between two returns: a tie, taken from the left
        assert torch.equal(interpolate_scan(scan, 2)[:, 0, 1], _nearest_by_search(scan)), scan


def test_path0_in_onnxruntime_matches_torch():
    import io
    from explorer.calibration.measure import session   # the process's thread pool, as the suite sets it up

    class Path0(torch.nn.Module):
        def forward(self, scan):
            return interpolate_scan(scan, 5)
    buf = io.BytesIO()
    torch.onnx.export(Path0(), (torch.rand(2, 37),), buf, opset_version=17, dynamo=False)
    sess = session(buf.getvalue())
    scan = torch.rand(2, 37, generator=torch.Generator().manual_seed(1)) * 10
    scan[0, ::2] = 0.0
    scan[1, 3:30] = 0.0
    np.testing.assert_array_equal(sess.run(None, {sess.get_inputs()[0].name: scan.numpy()})[0],
                                  interpolate_scan(scan, 5).numpy())


@pytest.mark.parametrize("depth", [1, 2])
def test_the_last_exit_head_up_samples_after_its_1x1_layers_with_the_same_values(depth):
    from dataclasses import replace
    cand = replace(paper_candidate(), head_depth=depth, head_width=8)
    torch.manual_seed(0)
    net = build_network(cand).eval()
    for m in net.modules():   # BatchNorm statistics away from identity, so that they take part
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-1, 1)
            m.running_var.uniform_(0.5, 2)
            m.bias.data.uniform_(-1, 1)
    specs = {s.name: s.config for s in net.specs}
    assert not specs["decoder_4"].upsample and specs["exit_4"].nearest == 2
    assert all(specs[f"decoder_{k}"].upsample for k in (1, 2, 3))
    reference = build_network(cand, paper_graph=True).eval()   # the paper's order
    reference.load_state_dict(net.state_dict())
    image, scan = torch.rand(2, 3, 64, 96), torch.rand(2, 96) * 5 + 0.5
    with torch.no_grad():
        got, want = net(image, scan), reference(image, scan)
    for g, w in zip(got, want):
        assert g.shape == w.shape == (2, 1, 64, 96)
        torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-5)


def test_a_last_decoder_stage_with_a_skip_or_without_an_exit_up_samples_itself():
    for cand in SearchSpace.from_yaml("anytime_depth").random_candidates(20, seed=3):
        for spec in stage_specs(cand):
            cfg = spec.config
            if spec.name.startswith("decoder_") and not cfg.upsample:
                last = f"decoder_{len(cand.decoder_widths)}"
                assert spec.name == last and not cfg.has_skip and len(cand.decoder_widths) in cand.exits


@pytest.mark.parametrize("shape,factor", [((2, 1, 14, 14), 16), ((1, 1, 7, 9), 3), ((1, 3, 5, 1), 2)])
def test_bilinear_up_sampling_as_matrix_products_matches_interpolate(shape, factor):
    import torch.nn.functional as F

    from explorer.model.ops import Resize
    x = torch.randn(shape)
    want = F.interpolate(x, scale_factor=float(factor), mode="bilinear", align_corners=False)
    torch.testing.assert_close(Resize(factor, "bilinear")(x), want, rtol=1e-5, atol=1e-5)


def test_the_ecu_band_follows_a_slanted_scan_line_column_by_column():
    from explorer.model.ops import BandCrop
    feature = torch.arange(8.0)[None, None, :, None].expand(2, 3, 8, 5).contiguous()   # value = its row
    rows = torch.tensor([[0, 2, 4, 6, 7], [3, 3, 3, 3, 3]])
    band = BandCrop(3)(feature, rows)
    # each column's three rows around its own row, clamped to the feature
    assert band[0, 0, :, 0].tolist() == [0, 1, 2] and band[0, 0, :, 2].tolist() == [3, 4, 5]
    assert band[0, 0, :, 4].tolist() == [5, 6, 7]
    assert torch.equal(band[1], BandCrop(3)(feature, 3)[1])      # one row for all columns: the slice


def test_the_network_takes_one_row_or_one_per_column():
    net = build_network(paper_candidate()).eval()
    with torch.no_grad():
        for p in net.stages["ecu"].compensation.parameters():   # a compensation that depends on the band
            torch.nn.init.normal_(p, std=0.5)
        image, scan = torch.rand(2, 3, 64, 64), torch.rand(2, 64) * 4 + 0.5
        corrected = []   # what the ECU adds to the image feature
        net.stages["ecu"].register_forward_hook(lambda m, args, out: corrected.append(out - args[0]))
        level = net(image, scan, 32)
        same = net(image, scan, torch.full((2, 64), 32))
        net(image, scan, torch.linspace(8, 56, 64).round().long().expand(2, 64))
    assert all(torch.equal(a, b) for a, b in zip(level, same))
    assert torch.equal(corrected[0], corrected[1]) and not torch.allclose(corrected[0], corrected[2])
    with pytest.raises(ValueError, match="per-column scan rows"):
        net(image, scan, torch.full((2, 32), 32))
