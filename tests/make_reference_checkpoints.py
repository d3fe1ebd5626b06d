"""Write random-weight checkpoints in the exact layout of the reference implementation's
published R2D2 series (basp-group/R2D2-RI v2), for the importer's tests.

    python3 tests/make_reference_checkpoints.py OUT --arch unet|uwdsr [--networks I]
        [--realisations R] [--channels C] [--poolings P] [--layers J] [--seed S]

writes OUT/R2D2_UNet_N{i}.ckpt (or R2D2_UWDSR_N{i}.ckpt; R3D3_UNet_{J}L_N{i}.ckpt with
--layers J > 1), or with R > 1 the same under OUT/V1 .. OUT/V{R}. Each file is what
`torch.save` of a PyTorch Lightning checkpoint holds: `epoch`, `global_step`,
`pytorch-lightning_version`, `state_dict` (parameters under the module's attribute: `unet.`,
or `unet1.` .. `unetJ.` for R3D3), `loops`, `callbacks`, `optimizer_states`, `lr_schedulers`,
`hparams_name` and `hyper_parameters`, an AttributeDict of the training arguments (pathlib
paths among them) pickled under Lightning's class name, so that loading it without Lightning
is exercised.

The U-Net's parameter names and shapes are spelt out below from the reference's module
structure, independently of training/r2d2train; the U-WDSR's come from
training/r2d2train/uwdsr.py, whose names are the reference's by design.
These are random weights, not the published networks (which cannot be downloaded here).
"""
import argparse
import collections
import os
import pathlib
import sys
import types

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "training"))


def attribute_dict_class():
    """Lightning's AttributeDict, or a stand-in pickled under its module and name."""
    try:
        from lightning.fabric.utilities.data import AttributeDict  # noqa: F401
        return AttributeDict
    except ImportError:
        pass
    names = ["lightning", "lightning.fabric", "lightning.fabric.utilities", "lightning.fabric.utilities.data"]
    for name in names:
        sys.modules.setdefault(name, types.ModuleType(name))
    cls = type("AttributeDict", (dict,), {"__module__": names[-1]})
    sys.modules[names[-1]].AttributeDict = cls
    return cls


def conv_block(prefix, cin, cout):
    # Conv(3x3, no bias), InstanceNorm, LeakyReLU, Dropout, Conv(3x3, no bias), ...: the
    # second convolution is module 4.
    return [(f"{prefix}.layers.0.weight", (cout, cin, 3, 3)), (f"{prefix}.layers.4.weight", (cout, cout, 3, 3))]


def reference_unet_parameters(chans, pools):
    params = conv_block("down_sample_layers.0", 2, chans)
    ch = chans
    for i in range(1, pools):
        params += conv_block(f"down_sample_layers.{i}", ch, ch * 2)
        ch *= 2
    params += conv_block("conv", ch, ch * 2)
    for i in range(pools):
        params.append((f"up_transpose_conv.{i}.layers.0.weight", (ch * 2, ch, 2, 2)))
        params += conv_block(f"up_conv.{i}" if i < pools - 1 else f"up_conv.{i}.0", ch * 2, ch)
        ch //= 2
    params += [(f"up_conv.{pools - 1}.1.weight", (1, chans, 1, 1)), (f"up_conv.{pools - 1}.1.bias", (1,))]
    return params


def random_unet(chans, pools, gen):
    out = collections.OrderedDict()
    for name, shape in reference_unet_parameters(chans, pools):
        fan_in = shape[1] * shape[2] * shape[3] if len(shape) == 4 else 1
        out[name] = torch.randn(shape, generator=gen) * (2.0 / fan_in) ** 0.5
    return out


def random_uwdsr(chans, pools, gen):
    from r2d2train.uwdsr import UWDSR
    net = UWDSR(chans, pools)
    out = collections.OrderedDict()
    for name, value in net.state_dict().items():
        if name.endswith("weight_g"):
            # Random gains near the reference's initial ones, so the blocks do not blow up.
            value = value * (0.5 + torch.rand(value.shape, generator=gen))
        elif name.endswith("bias"):
            value = 0.01 * torch.randn(value.shape, generator=gen)
        else:
            value = torch.randn(value.shape, generator=gen) * value.std()
        out[name] = value
    return out


def hyper_parameters(args, iteration):
    AttributeDict = attribute_dict_class()
    return AttributeDict(
        mode="train", num_epochs=50, num_pools=args.poolings, drop_prob=0.0, num_chans=args.channels,
        num_chans_in=2, num_chans_out=1, batch_size=1, lr=0.0001, lr_step_size=1000, lr_gamma=0.0,
        gradient_clip_val=0.01, weight_decay=0.0, positivity=iteration == 1, series="R2D2" if args.layers == 1 else "R3D3",
        layers=args.layers, num_iter=iteration, gpus=1, nodes=1, exp_dir=pathlib.PosixPath("experiments"),
        exp=f"N{iteration}", resume=False, checkpoint=None, data_path=pathlib.PosixPath("data/vla"),
        im_dim_x=512, im_dim_y=512, scname_train="trainingset_fullnumpy", scname_val="validationset_fullnumpy",
        scname_test="testset_fullnumpy", rec_ext="_recN1", rec_file_ext="_rec", res_ext="_resN1",
        dirty_file_ext="_dirty", res_file_ext="_dirty" if iteration == 1 else "_res", gdth_file_ext="_gdth",
        mat_ext=None, mat_file_ext=None, dirty_ext="_dirty", PSF_path=None, PSF_file_ext="_PSF",
        rec2_ext="_recN1", save_output=False, architecture=args.arch,
    )


def checkpoint(args, iteration, gen):
    state = collections.OrderedDict()
    prefixes = ["unet"] if args.layers == 1 else [f"unet{l}" for l in range(1, args.layers + 1)]
    for prefix in prefixes:
        weights = random_unet(args.channels, args.poolings, gen) if args.arch == "unet" else random_uwdsr(args.channels, args.poolings, gen)
        state.update((f"{prefix}.{k}", v) for k, v in weights.items())
    return {
        "epoch": 49,
        "global_step": 50 * 2000,
        "pytorch-lightning_version": "2.2.1",
        "state_dict": state,
        "loops": {"fit_loop": {"state_dict": {}, "epoch_progress": {"total": {"ready": 50, "completed": 49}}}},
        "callbacks": {"ModelCheckpoint{'monitor': 'val_loss', 'mode': 'min', 'every_n_train_steps': 0, 'every_n_epochs': 1, 'train_time_interval': None}": {
            "monitor": "val_loss", "best_model_score": torch.tensor(0.0123), "best_model_path": "experiments/ckpt/best.ckpt",
            "current_score": torch.tensor(0.0123), "dirpath": "experiments/ckpt", "best_k_models": {}, "kth_best_model_path": "",
            "kth_value": torch.tensor(float("inf")), "last_model_path": ""}},
        "optimizer_states": [{"state": {0: {"step": torch.tensor(100000.0), "square_avg": torch.zeros(3)}}, "param_groups": [
            {"lr": 0.0001, "alpha": 0.99, "eps": 1e-08, "weight_decay": 0.0, "momentum": 0, "centered": False, "params": [0]}]}],
        "lr_schedulers": [{"step_size": 1000, "gamma": 0.0, "base_lrs": [0.0001], "last_epoch": 49, "_step_count": 50}],
        "hparams_name": "hparams",
        "hyper_parameters": hyper_parameters(args, iteration),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out")
    ap.add_argument("--arch", choices=["unet", "uwdsr"], required=True)
    ap.add_argument("--networks", type=int, default=2)
    ap.add_argument("--realisations", type=int, default=1)
    ap.add_argument("--channels", type=int, default=None, help="base channels (default: the published 32 for unet, 64 for uwdsr)")
    ap.add_argument("--poolings", type=int, default=4)
    ap.add_argument("--layers", type=int, default=1)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    if args.channels is None:
        args.channels = 32 if args.arch == "unet" else 64
    stem = {"unet": "UNet", "uwdsr": "UWDSR"}[args.arch]
    stem = f"R2D2_{stem}" if args.layers == 1 else f"R3D3_{stem}_{args.layers}L"
    gen = torch.Generator().manual_seed(args.seed)
    for r in range(1, args.realisations + 1):
        d = args.out if args.realisations == 1 else os.path.join(args.out, f"V{r}")
        os.makedirs(d, exist_ok=True)
        for i in range(1, args.networks + 1):
            torch.save(checkpoint(args, i, gen), os.path.join(d, f"{stem}_N{i}.ckpt"))


if __name__ == "__main__":
    main()
