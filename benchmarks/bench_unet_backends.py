"""What makes one denoiser call faster on a CPU: the policy's traced U-Net (``inference_backend:
trace``) and other settings against a plain ``torch.jit.trace`` of LeRobot's U-Net (the learned-planner
issue's latency target: K = 10 candidates with the safety layer within 15 ms, where DDIM-4 sampling
alone takes about four U-Net calls at batch 10).

For each batch size in ``--batch`` (default 1, 10 and 100: one sample, best-of-10's candidates, a
batched engine), one U-Net call of the checkpoint's inference model (``--policy.path``, default the
shipped ``pretrained/formation_diffusion_route_v1``) on random inputs, median over ``--repeats`` calls
after a warm-up, with ``--threads`` torch threads:

- ``trace fp32``: ``torch.jit.trace`` + ``freeze`` of LeRobot's U-Net as it is (the policy's trace
  until 2026-12-05), the baseline;
- ``policy trace``: the policy's traced U-Net since 2026-12-05 (``_TracedUnet``: copies from
  ``policy.unet_inference``, matrix-product convolutions up to ``SMALL_BATCH_ROWS`` rows and
  oneDNN's above, Mish as x tanh(softplus(x)) in both);
- ``eager fp32``: the module as it is;
- ``trace bf16 autocast``: traced under ``torch.autocast("cpu", dtype=torch.bfloat16)``;
- ``trace + oneDNN fusion``: traced with ``torch.jit.enable_onednn_fusion(True)``;
- ``optimize_for_inference``: ``torch.jit.optimize_for_inference`` of the trace.

Each line gives the median [ms], the ratio to the baseline and the largest difference of the output
from the baseline's. The U-Net's multiply-adds per call (Conv1d, ConvTranspose1d and Linear layers,
counted with forward hooks) give the rate the baseline reaches [GFLOP/s]: far below what one core's
vector units do means the small convolutions' overhead, not arithmetic, bounds it.

Run::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_unet_backends.py --threads 1

The last line: the policy's trace against the baseline at each batch size (a ratio below 1 is a
speed-up).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch  # noqa: E402

from lerobot_formation.bench.timing import median_seconds  # noqa: E402
from lerobot_formation.threads import add_threads_argument, apply_threads  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def unet_flops(unet: torch.nn.Module, inputs: tuple) -> int:
    """Floating-point operations (2 per multiply-add) of one call on ``inputs``: its Conv1d,
    ConvTranspose1d and Linear layers, counted with forward hooks."""
    total = 0

    def hook(module, args, out):
        nonlocal total
        if isinstance(module, torch.nn.Conv1d):
            total += 2 * out.numel() * module.in_channels * module.kernel_size[0] // module.groups
        elif isinstance(module, torch.nn.ConvTranspose1d):
            total += 2 * args[0].numel() * module.out_channels * module.kernel_size[0]
        elif isinstance(module, torch.nn.Linear):
            total += 2 * out.numel() * module.in_features

    handles = [m.register_forward_hook(hook) for m in unet.modules()]
    try:
        with torch.inference_mode():
            unet(*inputs)
    finally:
        for h in handles:
            h.remove()
    return total


def variants(unet: torch.nn.Module, inputs: tuple) -> dict:
    """name -> a callable of no argument running one U-Net call on ``inputs`` (see the docstring)."""

    def trace():
        return torch.jit.freeze(torch.jit.trace(unet, inputs, check_trace=False).eval())

    with torch.inference_mode():
        base = trace()
        optimized = torch.jit.optimize_for_inference(torch.jit.trace(unet, inputs, check_trace=False).eval())
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        bf16 = trace()
    torch.jit.enable_onednn_fusion(True)
    try:
        with torch.no_grad():  # oneDNN graph fusion profiles its first calls outside inference mode
            fused = trace()
            for _ in range(3):
                fused(*inputs)
    finally:
        torch.jit.enable_onednn_fusion(False)

    def under(mode, fn, fusion=False):
        def call():
            torch.jit.enable_onednn_fusion(fusion)
            try:
                with mode():
                    return fn(*inputs)
            finally:
                torch.jit.enable_onednn_fusion(False)

        return call

    def autocast():
        return torch.autocast("cpu", dtype=torch.bfloat16)

    from lerobot_formation.policy.modeling_formation_diffusion import _TracedUnet

    with torch.inference_mode():
        policy_trace = _TracedUnet(unet, *inputs).fn
    if policy_trace is None:
        raise RuntimeError("the policy's trace of this U-Net failed (see the warning above)")
    return {
        "trace fp32": under(torch.inference_mode, base),
        "policy trace": under(torch.inference_mode, policy_trace),
        "eager fp32": under(torch.inference_mode, unet),
        "trace bf16 autocast": under(autocast, bf16),
        "trace + oneDNN fusion": under(torch.no_grad, fused, fusion=True),
        "optimize_for_inference": under(torch.inference_mode, optimized),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--policy.path", dest="policy_path", default=str(REPO / "pretrained" / "formation_diffusion_route_v1")
    )
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 10, 100], help="U-Net batch sizes")
    ap.add_argument("--repeats", type=int, default=100)
    add_threads_argument(ap, "torch threads")
    args = ap.parse_args(argv)
    if any(b < 1 for b in args.batch) or args.repeats < 1:
        ap.error(f"--batch and --repeats must be >= 1, got {args.batch} and {args.repeats}")
    apply_threads(args.threads)

    from lerobot_formation.policy.checkpoint import load_policy
    from lerobot_formation.policy.modeling_formation_diffusion import denoiser_parts

    policy, _, _ = load_policy(args.policy_path, "cpu")
    model = policy.inference_model
    unet, _, _, shape = denoiser_parts(model)
    cfg = policy.config  # low-dimensional inputs: the conditioning is the stacked observation history
    cond_dim = cfg.n_obs_steps * sum(feature.shape[0] for feature in cfg.input_features.values())
    generator = torch.Generator().manual_seed(0)
    ratios = []
    for batch in args.batch:
        inputs = (
            torch.randn(batch, *shape, generator=generator),
            torch.full((batch,), 50, dtype=torch.long),
            torch.randn(batch, cond_dim, generator=generator),
        )
        flops = unet_flops(unet, inputs)
        calls = variants(unet, inputs)
        with torch.inference_mode():
            want = calls["trace fp32"]().float()
        times = {}
        for name, call in calls.items():
            times[name] = 1e3 * median_seconds(call, args.repeats, warmup=3)
            with torch.inference_mode():
                diff = float((call().float() - want).abs().max())
            base = times["trace fp32"]
            print(
                f"B={batch} {name:<24} {times[name]:7.2f} ms  {times[name] / base:5.2f}x  max diff {diff:.1e}"
            )
        rate = flops / (times["trace fp32"] * 1e-3) / 1e9
        print(f"B={batch} {flops / 1e6:.1f} MFLOP per call: the traced fp32 U-Net runs at {rate:.1f} GFLOP/s")
        ratios.append(
            f"B={batch} {times['policy trace']:.2f} vs {times['trace fp32']:.2f} ms, ratio "
            f"{times['policy trace'] / times['trace fp32']:.2f}"
        )
    print(f"U-Net call, {args.threads} thread(s), policy trace vs plain trace: " + "; ".join(ratios))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
