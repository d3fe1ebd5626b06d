"""Checkpoints of the reference implementation (basp-group/R2D2-RI, v2): how they are laid out
on disk and how their networks are rebuilt here.

Accepted layouts (docs/models.md, "Importing the reference's checkpoints"):

- one realisation: `DIR/<stem>_N{i}.ckpt`, i = 1..I without gaps, one stem per directory
  (`R2D2_UNet`, `R2D2_UWDSR` as published; R3D3 series keep the same numbering);
- several realisations: `DIR/V{r}/<stem>_N{i}.ckpt`, r = 1..R, as the reference's imager
  reads them (`ckpt_realisations: R`), each with the same stem and I.

Each file is a PyTorch Lightning checkpoint: a dict whose `state_dict` holds the network's
parameters under the Lightning module's attribute (`unet.` for R2D2, whatever the name, since
the reference strips the first component; `unet1.` .. `unetJ.` for the J layers of an R3D3
component), and whose `hyper_parameters` (Lightning's AttributeDict of the training arguments:
`num_chans`, `num_pools`, `layers`, `im_dim_x`, ...) record how it was trained.

Checkpoints are pickles, which can run code when loaded: they are read here by an unpickler
that builds only tensors, containers, numbers and strings, and stands in plain values for
Lightning's and pathlib's classes, so neither Lightning nor trust in the file is needed.
"""
import collections
import hashlib
import os
import pickle
import re

import torch

from .unet import UNet
from .uwdsr import UWDSR, fold_weight_norm

# The published series' validity (the reference's README): 512 x 512 images, super-resolution
# factors 1.5..2.5, Briggs weighting with robustness -1..1.
PUBLISHED_VALIDITY = {"image_sizes": [512], "superresolution": [1.5, 2.5], "robust": [-1.0, 1.0], "weighting": ["briggs"]}

NAME = re.compile(r"^(?P<stem>.+)_N(?P<i>[1-9][0-9]*)\.ckpt$")
REALISATION = re.compile(r"^V(?P<r>[1-9][0-9]*)$")


class _Plain(dict):
    """Stands in for Lightning's AttributeDict and similar mappings."""


def _path_as_string(*parts):
    return os.path.join(*[str(p) for p in parts]) if parts else ""


# Globals a Lightning checkpoint may name, beyond torch's tensor rebuilding.
_ALLOWED = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("collections", "defaultdict"): collections.defaultdict,
    ("builtins", "set"): set,
    ("builtins", "frozenset"): frozenset,
    ("builtins", "slice"): slice,
    ("builtins", "complex"): complex,
    ("pathlib", "PosixPath"): _path_as_string,
    ("pathlib", "WindowsPath"): _path_as_string,
    ("pathlib", "Path"): _path_as_string,
    ("lightning.fabric.utilities.data", "AttributeDict"): _Plain,
    ("pytorch_lightning.utilities.parsing", "AttributeDict"): _Plain,
    ("lightning.pytorch.utilities.parsing", "AttributeDict"): _Plain,
    ("argparse", "Namespace"): _Plain,
    ("torch", "Size"): torch.Size,
    ("torch", "device"): torch.device,
    ("torch", "dtype"): torch.dtype,
    ("numpy.core.multiarray", "scalar"): None,
    ("numpy", "dtype"): None,
}


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if (module.startswith("torch") and (name.startswith("_rebuild_") or name.endswith("Storage"))) or (module, name) in {
            ("torch", "float32"), ("torch", "float16"), ("torch", "bfloat16"), ("torch", "float64"), ("torch", "int64"),
        }:
            return super().find_class(module, name)
        if (module, name) in _ALLOWED:
            found = _ALLOWED[(module, name)]
            if found is None:
                # numpy scalars in callback states: rebuilt by numpy itself (no code execution).
                return super().find_class(module, name)
            if found is _Plain and name == "Namespace":
                return lambda **kw: _Plain(kw)
            return found
        raise pickle.UnpicklingError(f"refusing to load {module}.{name} (not a tensor, container or Lightning value)")


class _RestrictedPickle:
    """A `pickle_module` for torch.load that builds only allow-listed globals."""

    Unpickler = _RestrictedUnpickler
    load = pickle.load
    __name__ = "r2d2_restricted_pickle"


def load_checkpoint(path):
    """The checkpoint's dict, read without running code from it."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False, pickle_module=_RestrictedPickle)
    except Exception as e:  # noqa: BLE001 - every failure is reported with the file named
        raise SystemExit(f"{path}: not a readable PyTorch Lightning checkpoint: {e}")
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict):
        raise SystemExit(f"{path}: expected a Lightning checkpoint (a dict with 'state_dict'), got keys {list(ckpt)[:8] if isinstance(ckpt, dict) else type(ckpt).__name__}")
    return ckpt


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def discover(directory):
    """[[path of N1, N2, ...] per realisation], the common stem, and whether V{r}/ was used."""
    entries = sorted(os.listdir(directory))
    subdirs = [e for e in entries if REALISATION.match(e) and os.path.isdir(os.path.join(directory, e))]
    if subdirs:
        numbers = sorted(int(REALISATION.match(e).group("r")) for e in subdirs)
        if numbers != list(range(1, len(numbers) + 1)):
            raise SystemExit(f"{directory}: expected realisation folders V1 .. V{len(numbers)} without gaps, found {['V%d' % n for n in numbers]}")
        dirs = [os.path.join(directory, f"V{r}") for r in numbers]
    else:
        dirs = [directory]
    realisations, stems = [], set()
    for d in dirs:
        found = {}
        for e in os.listdir(d):
            m = NAME.match(e)
            if m:
                stems.add(m.group("stem"))
                found[int(m.group("i"))] = os.path.join(d, e)
        if not found:
            raise SystemExit(f"{d}: no checkpoint named <stem>_N{{i}}.ckpt (e.g. R2D2_UNet_N1.ckpt, R2D2_UWDSR_N1.ckpt)")
        if sorted(found) != list(range(1, len(found) + 1)):
            raise SystemExit(f"{d}: expected networks N1 .. N{len(found)} without gaps, found {sorted(found)}")
        realisations.append([found[i] for i in sorted(found)])
    if len(stems) != 1:
        raise SystemExit(f"{directory}: expected one series name per directory, found {sorted(stems)}")
    lengths = {len(r) for r in realisations}
    if len(lengths) != 1:
        raise SystemExit(f"{directory}: realisations have different numbers of networks: {[len(r) for r in realisations]}")
    return realisations, stems.pop(), bool(subdirs)


def split_layers(state_dict, path):
    """{layer (1-based): state dict without the Lightning prefix}: one layer for R2D2 (any one
    prefix), J for R3D3 (`unet1.` .. `unetJ.`)."""
    prefixes = {k.split(".", 1)[0] for k in state_dict}
    if any("." not in k for k in state_dict):
        raise SystemExit(f"{path}: state_dict keys without a module prefix: not a Lightning checkpoint of the reference")
    numbered = {p: int(p[4:]) for p in prefixes if re.fullmatch(r"unet[1-9][0-9]*", p)}
    if numbered and len(numbered) == len(prefixes):
        layers = sorted(numbered.values())
        if layers != list(range(1, len(layers) + 1)):
            raise SystemExit(f"{path}: R3D3 layers unet1 .. unet{len(layers)} expected, found {sorted(prefixes)}")
        return {l: {k.split(".", 1)[1]: v for k, v in state_dict.items() if k.startswith(f"unet{l}.")} for l in layers}
    if len(prefixes) != 1:
        raise SystemExit(f"{path}: expected one network under one prefix (e.g. 'unet.'), or R3D3 layers 'unet1.' .. , found {sorted(prefixes)}")
    return {1: {k.split(".", 1)[1]: v for k, v in state_dict.items()}}


def architecture_of(weights):
    """'uwdsr' (weight-normalised) or 'unet', from the parameter names."""
    return "uwdsr" if any(k.endswith(".weight_g") for k in weights) else "unet"


def shape_of(weights, path):
    """(base channels, poolings) read from the parameters."""
    downs = {int(m.group(1)) for k in weights for m in [re.match(r"down_sample_layers\.(\d+)\.", k)] if m}
    if not downs or sorted(downs) != list(range(len(downs))):
        raise SystemExit(f"{path}: no down_sample_layers.0 .. parameters: not the reference's U-Net or U-WDSR")
    first = weights.get("down_sample_layers.0.layers.0.weight")
    if first is None:
        first = weights.get("down_sample_layers.0.skip.0.weight_v")
    if first is None:
        raise SystemExit(f"{path}: down_sample_layers.0 has neither layers.0.weight (U-Net) nor skip.0.weight_v (U-WDSR)")
    return int(first.shape[0]), len(downs)


_UNET_RENAMES = [(r"^down_sample_layers\.", "down."), (r"^conv\.", "bottom."), (r"^up_transpose_conv\.", "up."), (r"\.layers\.4\.", ".layers.3.")]


def reference_unet_to_project(weights):
    """The reference U-Net's names on the project's U-Net (training/r2d2train/unet.py): the same
    network (its dropouts of probability 0 are identities, which shifts the second convolution
    of each block from index 4 to 3)."""
    out = {}
    for k, v in weights.items():
        for pattern, repl in _UNET_RENAMES:
            k = re.sub(pattern, repl, k)
        out[k] = v
    return out


def build_network(weights, path):
    """The PyTorch network of one layer's weights, loaded strictly, in eval mode."""
    arch = architecture_of(weights)
    chans, pools = shape_of(weights, path)
    if arch == "uwdsr":
        net = UWDSR(chans, pools)
        state = weights
    else:
        net = UNet(chans, pools, norm="instance")
        state = reference_unet_to_project(weights)
    try:
        net.load_state_dict({k: v.float() for k, v in state.items()}, strict=True)
    except RuntimeError as e:
        raise SystemExit(f"{path}: parameters do not fit the reference {arch} with {chans} channels and {pools} poolings: {e}")
    net.eval()
    if arch == "uwdsr":
        fold_weight_norm(net)
    return net, arch, chans, pools


def plain_hyper_parameters(ckpt):
    """The checkpoint's hyper-parameters as YAML-safe values (others as their repr)."""
    hp = ckpt.get("hyper_parameters") or {}

    def plain(v):
        if isinstance(v, (bool, int, float, str)) or v is None:
            return v
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {str(k): plain(x) for k, x in v.items()}
        return repr(v)

    return {str(k): plain(v) for k, v in dict(hp).items()}
