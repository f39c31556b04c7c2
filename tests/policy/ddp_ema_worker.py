"""One rank of the 2-process EMA check (run by test_plugin_ema.py through torch.distributed.run).

Each rank trains the same tiny policy on its own batches, the way lerobot-train does under
``accelerate launch``: backward, optimizer step, then ``unwrap_model(policy).update()``. Rank 0
writes the ranks' ``ema_step`` and the largest EMA/live difference between ranks to argv[1].
"""

import faulthandler
import json
import sys

import torch
from accelerate import Accelerator
from accelerate.utils import DistributedDataParallelKwargs
from plugin_helpers import tiny_config, train_batch

from lerobot_formation.policy.modeling_formation_diffusion import FormationDiffusionPolicy

STEPS = 3


def flat(params) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in params])


def main(out_path: str) -> None:
    # A run takes seconds; if this rank is still here after 120 s (the test cuts it at 150 s), its stack
    # goes to the log the test prints, to show where it stalled.
    faulthandler.dump_traceback_later(120, exit=False)
    torch.set_num_threads(1)
    accelerator = Accelerator(
        cpu=True,
        step_scheduler_with_optimizer=False,
        kwargs_handlers=[DistributedDataParallelKwargs(find_unused_parameters=True)],
    )
    torch.manual_seed(0)
    policy = FormationDiffusionPolicy(tiny_config())
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-2)
    model, optimizer = accelerator.prepare(policy, optimizer)
    model.train()
    for i in range(STEPS):
        batch = train_batch(seed=100 * accelerator.process_index + i)  # each rank its own shard
        loss, _ = model.forward(batch)  # as lerobot-train calls the prepared policy
        accelerator.backward(loss)
        optimizer.step()
        optimizer.zero_grad()
        accelerator.unwrap_model(model, keep_fp32_wrapper=True).update()
    ema = accelerator.gather(flat(policy.ema_diffusion.parameters())[None])
    live = accelerator.gather(flat(policy.diffusion.parameters())[None])
    steps = accelerator.gather(policy.ema_step.reshape(1))
    if accelerator.is_main_process:
        result = {
            "num_processes": accelerator.num_processes,
            "ema_steps": steps.tolist(),
            "ema_rank_gap": (ema[0] - ema[1]).abs().max().item(),
            "live_rank_gap": (live[0] - live[1]).abs().max().item(),
            "ema_live_gap": (ema[0] - live[0]).abs().max().item(),
        }
        with open(out_path, "w") as f:
            json.dump(result, f)
    accelerator.wait_for_everyone()
    # Tear the gloo group down before exit: left to the interpreter's shutdown, a rank can abort with
    # "terminate called without an active exception" (seen once in CI after a passing run).
    if torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
    faulthandler.cancel_dump_traceback_later()


if __name__ == "__main__":
    main(sys.argv[1])
