"""Coarse stage: the soft-alignment network, run from a TorchScript file.

A model file is a TorchScript archive whose ``forward(source (B, N, 3), target (B, M, 3))``
returns ``(R (B, 3, 3), t (B, 3), w (B, N))`` on normalised clouds, with an extra file
``o3dsoft.json`` describing it (format version, network config, how it was trained). The default
model ships inside the package (``o3dsoft/weights/``).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import threading
import warnings
import zipfile
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, NamedTuple, Optional, Tuple, Union

import numpy as np
import torch

from .errors import InputError, UntrustedModelWarning, UsageError, caller_stacklevel, first_line
from .io import atomic_output, make_folder
from .model import NetConfig, SoftAlignNet, ball_query
from .transforms import apply_transform, rigid

FORMAT = "o3dsoft-softalign"
FORMAT_VERSION = 1
META_NAME = "o3dsoft.json"
CPU_BATCH = 2  # clouds per network call on the CPU (see CoarseModel.aligner)
MAX_WEIGHT = 1e8  # larger parameter values are taken for a corrupted file: trained ones stay far below


_TORCH_RAN = [False]  # whether o3dsoft has run torch in this process (a network, a registration)


def torch_runs() -> None:
    """Note that o3dsoft runs torch in this process: a process it forks from now on runs torch on
    one thread (:func:`_one_thread_after_fork`)."""
    _TORCH_RAN[0] = True


def _one_thread_after_fork() -> None:
    if _TORCH_RAN[0]:
        torch.set_num_threads(1)


# A forked child inherits torch's OpenMP thread pool without its threads: its first parallel
# operation waits for them forever (Linux's default "fork" start method, after the parent has run
# a network). With one thread the child runs every operation itself, as torch's DataLoader
# workers do. Forks of a process where o3dsoft ran no torch keep their threads.
os.register_at_fork(after_in_child=_one_thread_after_fork)


_WARNED: set = set()


@contextmanager
def _quiet_jit() -> Iterator[None]:
    """Silence torch's deprecation notice for TorchScript, the format this project ships."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="`torch.jit", category=DeprecationWarning)
        yield


def default_weights_path() -> Path:
    """The model shipped with the package."""
    return bundled_weights_path("default")


def bundled_weights_path(name: str) -> Path:
    """The shipped model of that name: "default" or "paper" (weights/o3dsoft_<name>.pt)."""
    return Path(str(resources.files("o3dsoft.weights").joinpath(f"o3dsoft_{name}.pt")))


def bundled_model_names() -> List[str]:
    """Names of the models shipped with the package, for ``load_model("paper")``."""
    folder = resources.files("o3dsoft.weights")
    return sorted(f.name[len("o3dsoft_") : -len(".pt")] for f in folder.iterdir() if f.name.startswith("o3dsoft_") and f.name.endswith(".pt"))


def _shipped_card(path: Path) -> Optional[Dict[str, Any]]:
    """The model card of a shipped model file (weights/o3dsoft_<name>.json), else None."""
    for name in bundled_model_names():
        shipped = bundled_weights_path(name)
        if shipped.is_file() and path.resolve() == shipped.resolve():
            card = shipped.with_suffix(".json")
            return json.loads(card.read_text()) if card.is_file() else {}
    return None


def _check_origin(path: Path) -> None:
    """A shipped model must match the sha256 of its card; any other file is a program from
    elsewhere, said once per file."""
    card = _shipped_card(path)
    if card is None:
        key = str(path.resolve())
        if key not in _WARNED:
            _WARNED.add(key)
            warnings.warn(
                f"{path}: a model file is a TorchScript program that runs when used; load only files from a trusted source",
                UntrustedModelWarning,
                stacklevel=caller_stacklevel(),
            )
    elif card.get("sha256") and sha256_of(path) != card["sha256"]:
        raise InputError(f"{path}: the shipped model file does not match the sha256 of its card (modified or damaged); reinstall o3dsoft")


def _check_archive(path: Path) -> None:
    """Every member of the model's zip archive matches its CRC (TorchScript does not check)."""
    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
            names = archive.namelist()
    except (zipfile.BadZipFile, OSError) as e:
        raise InputError(f"{path}: not a readable TorchScript model file ({e})") from None
    if bad is not None:
        raise InputError(f"{path}: the model file is corrupted ({bad} fails its checksum)")
    if not any("/code/" in name for name in names):  # torch.save's archive: tensors, no program
        raise InputError(f"{path}: a training checkpoint (o3dsoft train's checkpoint.pt), not a model file: use the model.pt train exports beside it")


def non_finite_weight(weights: Dict[str, Any]) -> Optional[str]:
    """The name of the first floating tensor of a state dict that holds NaN or infinite values;
    None when there is none."""
    for name, tensor in weights.items():
        if torch.is_tensor(tensor) and tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            return name
    return None


def _check_values(module: torch.jit.ScriptModule, path: Path) -> None:
    """Every parameter and buffer is finite and of a plausible size."""
    weights = module.state_dict()
    bad = non_finite_weight(weights)
    if bad is not None:
        raise InputError(f"{path}: the model's {bad} holds NaN or infinite values (a corrupted file)")
    for name, tensor in weights.items():
        if tensor.is_floating_point() and tensor.numel() and float(tensor.abs().max()) > MAX_WEIGHT:
            raise InputError(f"{path}: the model's {name} holds values above {MAX_WEIGHT:g} (a corrupted file)")


def torch_device(name: Union[str, torch.device]) -> torch.device:
    """The torch device `name` ("cpu", "cuda", "cuda:1", "mps") names, if this machine has it.

    Raises:
        UsageError: no such device type, or this torch build does not see it.
    """
    try:
        device = torch.device(name)
    except RuntimeError:
        raise UsageError(f"invalid device {str(name)!r}: expected cpu, cuda, cuda:N or mps") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise UsageError(f"device {str(name)!r} was asked for but this torch build sees no CUDA GPU")
        if device.index is not None and device.index >= count:
            raise UsageError(f"device {str(name)!r} was asked for but this machine has {count} CUDA GPU(s), cuda:0 to cuda:{count - 1}")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise UsageError(f"device {str(name)!r} was asked for but this torch build sees no Apple GPU")
    elif device.type not in ("cpu", "cuda", "mps"):
        raise UsageError(f"invalid device {str(name)!r}: expected cpu, cuda, cuda:N or mps")
    return device


def sha256_of(path: Union[str, Path]) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def export_torchscript(model: SoftAlignNet, config: NetConfig, path: Union[str, Path], info: Optional[Dict[str, Any]] = None) -> Path:
    """Script `model` (in eval mode, on the CPU) and write it atomically with its metadata.

    Args:
        model: a trained network.
        config: its architecture settings (stored in the file).
        path: where to write the ``.pt`` file.
        info: extra facts to store (training protocol, epochs...).
    Returns:
        The path written.
    """
    path = Path(path)
    was_training = model.training
    model = model.eval()
    model.forget_last_call()
    device = next(model.parameters()).device
    with _quiet_jit():
        scripted = torch.jit.script(model.cpu())
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "net": config.to_dict(), "info": info or {}}
    make_folder(path.parent)
    # Saved into memory first: a file's archive takes its folder name from the file's name, the
    # temporary one's here, and the same weights would give files of different bytes (and sha256).
    archive = io.BytesIO()
    try:
        with _quiet_jit():
            torch.jit.save(scripted, archive, _extra_files={META_NAME: json.dumps(meta)})
        with atomic_output(path) as tmp:  # a failed write (e.g. a full disk): InputError, naming the file
            tmp.write_bytes(archive.getvalue())
    finally:
        model.to(device).train(was_training)
    return path


def rescript(model: "CoarseModel", path: Union[str, Path]) -> Path:
    """Write `model`'s weights and metadata to `path` again, scripted with the current code.

    A TorchScript file carries the inference code of the release that exported it; this brings
    a trained model's file up to date without its training checkpoint.
    """
    config = model.config
    net = SoftAlignNet(config)
    net.load_state_dict({k: v.cpu() for k, v in model.module.state_dict().items()})
    return export_torchscript(net, config, path, model.meta.get("info"))


@dataclass
class CoarseModel:
    """A loaded TorchScript soft-alignment model and what its file says about it."""

    module: torch.jit.ScriptModule
    meta: Dict[str, Any]
    path: Path
    device: torch.device

    @property
    def config(self) -> NetConfig:
        return NetConfig.from_dict(self.meta["net"])

    def run(self, source: torch.Tensor, target: torch.Tensor):
        """Raw network call: (B, N, 3), (B, M, 3) normalised clouds -> (R, t, w)."""
        with self.inference():
            return self.module(source.to(self.device), target.to(self.device))

    @contextmanager
    def inference(self) -> Iterator[None]:
        """No gradients, and on the CPU no optimising graph executor: TorchScript's profiling
        runs cost 0.1-0.2 s on each of the first two calls per input shape (most of a CLI
        ``register`` call's network time) and make later calls no faster there (docs/speed.md).
        Elsewhere the executor is left as the caller set it."""
        executor = torch.jit.optimized_execution(False) if self.device.type == "cpu" else nullcontext()
        torch_runs()
        with torch.no_grad(), executor:
            yield

    def neighbours(self, points: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) -> (B, N, K) int64 neighbour indices, the sets of the network's ball query.

        On the CPU through Open3D's KD-tree (its K nearest, then capped at the radius), several
        times faster than the network's top-k over all N^2 distances; the sets are the same, and
        their order does not matter at inference (a max over each neighbourhood). Elsewhere
        :func:`o3dsoft.model.ball_query`.
        """
        k, radius = self.config.k, self.config.radius
        if self.device.type != "cpu":
            return ball_query(points.to(self.device), k, radius)
        from ._open3d import open3d  # here, so that training (o3dsoft.train) runs where Open3D is not installed

        o3c = open3d.core
        out = []
        for cloud in points.detach().float().numpy():
            cloud = o3c.Tensor(np.ascontiguousarray(cloud))
            search = o3c.nns.NearestNeighborSearch(cloud)
            search.knn_index()
            idx, d2 = search.knn_search(cloud, k)  # each point's K nearest in its own cloud, itself first
            idx, d2 = torch.from_numpy(idx.numpy()).long(), torch.from_numpy(d2.numpy())
            # Neighbours beyond the radius become the point itself, as in ball_query.
            out.append(torch.where(d2 > radius * radius, idx[:, :1], idx))
        return torch.stack(out)

    def aligner(self, target: torch.Tensor) -> Callable[..., Tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """A function run(source (B, N, 3), idx=None) -> (R, t, w) aligning sources to one target
        (1, M, 3), whose descriptors are computed once, at the first call.

        idx: the source's neighbours (B or 1, N, K) from :meth:`neighbours`, computed by the
        caller once for a source it moves rigidly (neighbourhoods do not change); None: computed
        in each call. Model files written before ``align`` existed fall back to the plain call.
        """
        target = target.to(self.device)
        if not hasattr(self.module, "align"):
            return lambda source, idx=None: self.run(source, target.expand(source.shape[0], -1, -1))
        target_descriptors: List[torch.Tensor] = []

        def run(source: torch.Tensor, idx: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            source = source.to(self.device)
            idx = self.neighbours(source) if idx is None else idx.to(self.device).expand(source.shape[0], -1, -1)
            with self.inference():
                if not target_descriptors and self.config.shared_encoder and source.shape[0] == 1 and source.shape == target.shape:
                    # One encoder call on the pair: faster on the CPU than two calls of one cloud each.
                    both = self.module.describe_target(torch.cat([target, source]), torch.cat([self.neighbours(target), idx]))
                    target_descriptors.append(both[:1])
                    return self.module.align(source, both[1:], target, both[:1])
                if not target_descriptors:
                    target_descriptors.append(self.module.describe_target(target, self.neighbours(target)))
                g = target_descriptors[0]
                # On the CPU, a few clouds at a time keep the gather-max's working set in cache.
                step = CPU_BATCH if self.device.type == "cpu" else source.shape[0]
                parts = []
                for s in range(0, source.shape[0], step):
                    f = self.module.describe_source(source[s : s + step], idx[s : s + step])
                    parts.append(self.module.align(source[s : s + step], f, target, g))
            return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts]), torch.cat([p[2] for p in parts])

        return run


def weights_file(path: Union[str, Path, None] = None) -> Path:
    """The model file that `path` names: a file, a shipped model's name, or None for "default".

    Raises:
        UsageError: no such file or shipped model, or a folder.
    """
    if path is None:
        return default_weights_path()
    if not Path(path).is_file() and str(path) in bundled_model_names():
        return bundled_weights_path(str(path))
    path = Path(path)
    if path.is_dir():
        raise UsageError(f"{path}: is a folder; expected a model file (.pt)")
    if not path.is_file():
        raise UsageError(f"{path}: weights file not found (shipped models, by name: {', '.join(bundled_model_names())})")
    return path


def load_model(path: Union[str, Path, None] = None, device: Union[str, torch.device] = "cpu") -> CoarseModel:
    """Load a TorchScript model file, or a shipped model by name.

    Args:
        path: a model file; the name of a shipped model ("default", "paper"); None: "default".
        device: where the network runs ("cpu", "cuda", "cuda:1").
    A shipped model is checked against the sha256 of its card; any other file is a TorchScript
    program, and loading it warns once (:class:`UntrustedModelWarning`). The archive's checksums
    and the finiteness of every tensor are checked, so that a damaged file fails here.

    Raises:
        UsageError: the file is missing, or the device is unknown or absent.
        InputError: the file is damaged, is not a TorchScript archive, or is not an o3dsoft
            model; a shipped model does not match its card. Both are ValueErrors.
    """
    path = weights_file(path)
    device = torch_device(device)
    _check_archive(path)  # first: a file that is no model gets no warning about what it would run
    _check_origin(path)
    extra = {META_NAME: ""}
    try:
        with _quiet_jit():
            module = torch.jit.load(str(path), map_location=device, _extra_files=extra)
    except Exception as e:  # torch raises RuntimeError or ValueError, with long C++ traces
        raise InputError(f"{path}: not a readable TorchScript model file ({first_line(e)})") from None
    try:
        meta = json.loads(extra[META_NAME])
    except json.JSONDecodeError:
        meta = None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"{path}: a TorchScript file, but not an o3dsoft model (no {META_NAME} with format {FORMAT!r})")
    if meta.get("format_version", 0) > FORMAT_VERSION:
        raise InputError(f"{path}: model format version {meta['format_version']} is newer than this o3dsoft supports ({FORMAT_VERSION})")
    _check_values(module, path)
    module.eval()
    model = CoarseModel(module, meta, path, device)
    _check_contract(model)
    return model


_LOADED: Dict[Tuple[str, str, int], CoarseModel] = {}
_LOADING = threading.Lock()


def cached_model(path: Union[str, Path, None] = None, device: str = "cpu") -> CoarseModel:
    """:func:`load_model`, once per process for each file (as last modified) and device: for
    callers that register many pairs, and for the networks :func:`o3dsoft.register` loads itself."""
    name = str(path) if path is not None else "default"
    file = Path(name) if Path(name).is_file() else None
    key = (name, str(device), file.stat().st_mtime_ns if file else 0)
    with _LOADING:  # threads making their first call at once load the file once
        if key not in _LOADED:
            _LOADED[key] = load_model(path, device)
        return _LOADED[key]


def check_loaded(given: Any, name: str, setting: str) -> None:
    """Raise UsageError unless `given`, a caller's argument `name`, is None or a network
    :func:`load_model` loaded (or an object that stands in for one: its ``config`` and ``run``); a
    model's name or file instead says to name it in `setting`."""
    if given is None or isinstance(given, CoarseModel) or (hasattr(given, "config") and callable(getattr(given, "run", None))):
        return
    if isinstance(given, (str, os.PathLike)):
        raise UsageError(f"{name} is a loaded network (o3dsoft.coarse.load_model), got the name {str(given)!r}: name a model in {setting}")
    raise UsageError(f"{name} must be a network o3dsoft.coarse.load_model loaded, got {type(given).__name__}")


def _check_contract(model: CoarseModel) -> None:
    """Run the network once on two small random clouds and check what it returns, so that a
    file whose o3dsoft.json describes another network fails here, in one line."""
    try:
        k = model.config.k
        generator = torch.Generator().manual_seed(0)
        source, target = torch.rand(1, k + 8, 3, generator=generator) - 0.5, torch.rand(1, k + 5, 3, generator=generator) - 0.5
        with torch.jit.optimized_execution(False):  # a plain run: no profiling, no optimisation kept for these shapes
            R, t, w = model.run(source, target)
        ok = tuple(R.shape) == (1, 3, 3) and tuple(t.shape) == (1, 3) and tuple(w.shape) == (1, k + 8)
    except Exception as e:  # whatever a foreign network raises
        raise InputError(f"{model.path}: its network does not run as an o3dsoft model ({first_line(e)})") from None
    if not ok:
        raise InputError(
            f"{model.path}: its network returns {tuple(R.shape)}, {tuple(t.shape)}, {tuple(w.shape)}; an o3dsoft model returns R (B, 3, 3), t (B, 3), w (B, N)"
        )


class CoarseEstimate(NamedTuple):
    """Coarse stage output in the normalised frame: T (4, 4) float64 and weights w (N,) in [1/M, 1]."""

    transform: np.ndarray
    weights: np.ndarray


def estimate(model: CoarseModel, source: np.ndarray, target: np.ndarray, iterations: int = 1) -> CoarseEstimate:
    """Run the network on one normalised pair, `iterations` times.

    Each further pass runs the network on the source moved by the estimate so far (re-centred,
    as the network expects) and composes the correction, like the iterations of DCP or RPM-Net:
    the network is more precise on the smaller residual rotation.

    Args:
        model: a loaded model.
        source: (N, 3) normalised source points, N >= the model's K.
        target: (M, 3) normalised target points, M >= K.
        iterations: network passes (1: the paper's single pass).
    Returns:
        CoarseEstimate with T_target_source in the normalised frame and the last pass's weights.
    """
    if iterations < 1:
        raise InputError(f"coarse iterations must be at least 1, got {iterations}")
    run = model.aligner(torch.as_tensor(np.ascontiguousarray(target), dtype=torch.float32).unsqueeze(0))
    T = np.eye(4)
    source = np.asarray(source, dtype=np.float64)
    idx = model.neighbours(torch.as_tensor(source, dtype=torch.float32).unsqueeze(0))  # kept by rigid moves
    for _ in range(iterations):
        moved = apply_transform(T, source)
        centre = moved.mean(axis=0)
        src = torch.as_tensor(moved - centre, dtype=torch.float32).unsqueeze(0)
        R, t, w = run(src, idx)
        R_np, t_np = R[0].double().cpu().numpy(), t[0].double().cpu().numpy()
        T = rigid(R_np, t_np - R_np @ centre) @ T  # the step maps `moved` (not re-centred) onto the target
    return CoarseEstimate(T, w[0].float().cpu().numpy())
