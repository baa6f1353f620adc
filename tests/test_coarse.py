import numpy as np
import pytest
import torch

from o3dsoft.coarse import load_model
from o3dsoft.errors import InputError, UsageError
from o3dsoft.metrics import rotation_error_deg
from o3dsoft.transforms import rotation_angle_deg

from .conftest import apply, blob, python_output, random_transform
from .fakes import HalfwayModel


def test_bad_weights(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(InputError, match="junk.pt: not a readable TorchScript model file"):
        load_model(tmp_path / "junk.pt")
    import torch

    other = torch.jit.script(torch.nn.Linear(3, 3))
    other.save(str(tmp_path / "other.pt"))
    with pytest.raises(InputError, match="other.pt: a TorchScript file, but not an o3dsoft model"):
        load_model(tmp_path / "other.pt")
    with pytest.raises(UsageError, match="weights file not found"):
        load_model(tmp_path / "missing.pt")


def test_shipped_models_load_by_name(tmp_path, monkeypatch):
    from o3dsoft.coarse import bundled_model_names

    assert {"default", "paper"} <= set(bundled_model_names())
    paper = load_model("paper")
    assert paper.path.name == "o3dsoft_paper.pt" and paper.meta["info"]["protocol"] == "paper"
    assert load_model("default").meta["info"]["protocol"] == "wide45"
    with pytest.raises(UsageError, match="shipped models, by name: default, incongruent, paper"):
        load_model("nonesuch")
    # A file of that name in the working folder wins over the shipped model.
    import shutil

    shutil.copy(paper.path, tmp_path / "default")
    monkeypatch.chdir(tmp_path)
    assert load_model("default").meta["info"]["protocol"] == "paper"


@pytest.mark.parametrize("iterations", [1, 2, 3])
def test_coarse_iterations_compose_the_corrections(iterations):
    from o3dsoft.coarse import estimate

    rng = np.random.default_rng(3)
    source = blob(rng, 200) * 0.5
    T_gt = random_transform(rng, 40.0, 0.3)
    target = apply(T_gt, source)
    T = estimate(HalfwayModel(), source, target - target.mean(0), iterations).transform
    angle = rotation_angle_deg(T_gt[:3, :3])
    # Each pass halves the remaining rotation; the composition must keep the points in step.
    assert rotation_error_deg(T[:3, :3], T_gt[:3, :3]) == pytest.approx(angle / 2**iterations, rel=1e-3)
    residual = apply(T, source) - (target - target.mean(0))
    assert np.abs(residual.mean(0)).max() < 1e-5  # centroids coincide after every pass


def test_aligner_matches_the_plain_call_also_for_files_without_align(tiny_model_path, tmp_path):
    import json

    import torch

    from o3dsoft.coarse import META_NAME

    class ForwardOnly(torch.nn.Module):
        """A model file as written before describe_target/align were exported."""

        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, source, target):
            return self.net(source, target)

    model = load_model(tiny_model_path)
    old_path = tmp_path / "forward_only.pt"
    torch.jit.save(torch.jit.script(ForwardOnly(model.module)), str(old_path), _extra_files={META_NAME: json.dumps(model.meta)})
    old = load_model(old_path)
    assert not hasattr(old.module, "align") and hasattr(model.module, "align")
    rng = np.random.default_rng(0)
    src = torch.as_tensor(rng.normal(size=(4, 80, 3)) * 0.4, dtype=torch.float32)
    tgt = torch.as_tensor(rng.normal(size=(1, 70, 3)) * 0.4, dtype=torch.float32)
    expected = model.run(src, tgt.expand(4, -1, -1))
    for m in (model, old):
        for a, b in zip(m.aligner(tgt)(src), expected):
            assert torch.allclose(a, b, atol=1e-6)


def test_aligner_describes_a_same_size_pair_in_one_batch_with_the_same_result(tiny_model_path):
    import torch

    model = load_model(tiny_model_path)
    assert model.config.shared_encoder
    rng = np.random.default_rng(1)
    tgt = torch.as_tensor(rng.normal(size=(1, 70, 3)) * 0.4, dtype=torch.float32)
    first, later = (torch.as_tensor(rng.normal(size=(1, 70, 3)) * 0.4, dtype=torch.float32) for _ in range(2))
    run = model.aligner(tgt)
    for src in (first, later, first):  # the batched first call, then the cached target descriptors
        for a, b in zip(run(src), model.run(src, tgt)):
            assert torch.allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_open3d_neighbourhoods_are_the_ball_query_sets(tiny_model_path, seed):
    import torch

    from o3dsoft.model import ball_query

    model = load_model(tiny_model_path)
    k, radius = model.config.k, model.config.radius
    rng = np.random.default_rng(seed)
    # A dense clump (more than K points within the radius), a sparse spread and lone points.
    clouds = np.concatenate([rng.normal(size=(150, 3)) * 0.05, rng.uniform(-1, 1, size=(100, 3)), [[5.0, 5, 5], [-5, 5, 5]]])
    points = torch.as_tensor(clouds[rng.permutation(len(clouds))], dtype=torch.float32)[None]
    fast, reference = model.neighbours(points)[0], ball_query(points, k, radius)[0]
    assert fast.shape == reference.shape == (len(clouds), k)
    assert all(set(a.tolist()) == set(b.tolist()) for a, b in zip(fast, reference))
    assert (fast[:, 0] == torch.arange(len(clouds))).all()  # the point itself, always


def _copy(src, dst):
    dst.write_bytes(src.read_bytes())
    return dst


def test_a_model_file_damaged_in_its_tensor_data_is_refused(tiny_model_path, tmp_path):
    import zipfile

    path = _copy(tiny_model_path, tmp_path / "damaged.pt")
    with zipfile.ZipFile(path) as archive:
        member = next(i for i in archive.infolist() if "/data/" in i.filename and i.file_size > 64)
    raw = bytearray(path.read_bytes())
    name_length, extra_length = (int.from_bytes(raw[member.header_offset + k : member.header_offset + k + 2], "little") for k in (26, 28))
    start = member.header_offset + 30 + name_length + extra_length  # after the local header (its own padding) comes the data
    raw[start + 17] ^= 0x01  # one bit of one weight
    path.write_bytes(bytes(raw))
    with pytest.raises(InputError, match="damaged.pt: the model file is corrupted"):
        load_model(path)


@pytest.mark.parametrize("value, match", [(float("nan"), "NaN or infinite"), (1e30, "values above")])
def test_a_model_whose_weights_are_not_plausible_numbers_is_refused(tmp_path, value, match):
    import torch

    from o3dsoft.coarse import export_torchscript
    from o3dsoft.model import SoftAlignNet

    from .conftest import TINY

    net = SoftAlignNet(TINY)
    with torch.no_grad():
        max(net.parameters(), key=lambda p: p.numel()).view(-1)[3] = value
    path = export_torchscript(net, TINY, tmp_path / "bad.pt")
    with pytest.raises(InputError, match=match):
        load_model(path)


def test_the_same_weights_export_to_the_same_bytes_under_any_name(tmp_path):
    """A model file's sha256 (its card's) names its weights: two runs that end with the same
    weights give the same file, whatever it is called (a TorchScript archive written to a file
    takes the file's name inside it)."""
    from o3dsoft.coarse import export_torchscript, sha256_of
    from o3dsoft.model import SoftAlignNet

    from .conftest import TINY

    torch.manual_seed(0)
    net = SoftAlignNet(TINY)
    a = export_torchscript(net, TINY, tmp_path / "run_a" / "model.pt", {"epochs": 1})
    b = export_torchscript(net, TINY, tmp_path / "other name.pt", {"epochs": 1})
    assert sha256_of(a) == sha256_of(b)
    assert load_model(b).config == TINY


def test_shipped_models_are_checked_against_their_card_and_other_files_warn_once(tiny_model_path, tmp_path, monkeypatch):
    import json

    import o3dsoft.coarse as coarse
    from o3dsoft.coarse import UntrustedModelWarning, sha256_of

    shipped = _copy(tiny_model_path, tmp_path / "o3dsoft_tiny.pt")
    monkeypatch.setattr(coarse, "bundled_model_names", lambda: ["tiny"])
    monkeypatch.setattr(coarse, "bundled_weights_path", lambda name: tmp_path / f"o3dsoft_{name}.pt")
    (tmp_path / "o3dsoft_tiny.json").write_text(json.dumps({"sha256": sha256_of(shipped)}))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a shipped model that matches its card: no warning
        load_model("tiny")
    (tmp_path / "o3dsoft_tiny.json").write_text(json.dumps({"sha256": "0" * 64}))
    with pytest.raises(InputError, match="does not match the sha256 of its card"):
        load_model("tiny")
    other = _copy(tiny_model_path, tmp_path / "downloaded.pt")
    with pytest.warns(UntrustedModelWarning, match="downloaded.pt: a model file is a TorchScript program") as caught:
        load_model(other)
        load_model(other)
    assert len([w for w in caught if w.category is UntrustedModelWarning]) == 1


def test_the_untrusted_model_warning_names_the_users_line(tiny_model_path, tmp_path):
    # However deep inside o3dsoft the file is loaded, the warning points at the caller's line,
    # where a warnings filter by module or line can silence it.
    import o3dsoft

    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(300, 3))
    for i, call in enumerate(
        (load_model, lambda p: o3dsoft.register(cloud, cloud, o3dsoft.RegisterConfig(weights=str(p), search=o3dsoft.SearchConfig(mode="off"))))
    ):
        other = _copy(tiny_model_path, tmp_path / f"downloaded{i}.pt")
        with pytest.warns(o3dsoft.UntrustedModelWarning) as caught:
            call(other)
        (warning,) = [w for w in caught if w.category is o3dsoft.UntrustedModelWarning]
        assert warning.filename == __file__


class _Echo(torch.nn.Module):
    def forward(self, source: torch.Tensor, target: torch.Tensor):
        return source, target, source


@pytest.mark.parametrize("module, match", [(torch.nn.Linear(3, 3), "its network does not run as an o3dsoft model"), (_Echo(), "its network returns")])
def test_a_file_whose_card_describes_another_network_is_refused(tmp_path, module, match):
    import json

    from o3dsoft.coarse import FORMAT, FORMAT_VERSION, META_NAME
    from o3dsoft.model import NetConfig

    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "net": NetConfig().to_dict(), "info": {}}
    torch.jit.script(module).save(str(tmp_path / "impostor.pt"), _extra_files={META_NAME: json.dumps(meta)})
    with pytest.raises(InputError, match=f"impostor.pt: {match}"):
        load_model(tmp_path / "impostor.pt")


def test_cpu_inference_runs_without_the_optimising_graph_executor(tiny_model_path):
    # Its profiling runs cost 0.1-0.2 s on each of the first two calls per input shape on the CPU.
    model = load_model(tiny_model_path)
    module, seen = model.module, []

    def recording(*args):
        seen.append((torch._C._get_graph_executor_optimize(), torch.is_grad_enabled()))
        return module(*args)

    model.module = recording  # type: ignore[assignment]
    before = torch._C._get_graph_executor_optimize()
    model.run(torch.rand(1, 40, 3) - 0.5, torch.rand(1, 40, 3) - 0.5)
    assert seen == [(False, False)] and torch._C._get_graph_executor_optimize() == before


def test_a_fork_keeps_its_threads_until_o3dsoft_runs_torch():
    code = (
        "import os, torch, o3dsoft.coarse as c\n"
        "torch.set_num_threads(2)\n"
        "def child():\n"
        "    pid = os.fork()\n"
        "    if pid == 0:\n"
        "        os._exit(torch.get_num_threads())\n"
        "    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])\n"
        "before = child()\n"
        "c.torch_runs()\n"
        "print(before, child())\n"
    )
    assert python_output(code, timeout=120).split() == ["2", "1"]
