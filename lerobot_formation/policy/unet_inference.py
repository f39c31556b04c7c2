"""CPU inference copies of the U-Net: its 1-D convolutions as single matrix products for few rows,
and its Mish activations as x tanh(softplus(x)).

On a CPU, torch runs ``nn.Conv1d`` through oneDNN, which is built for large inputs. A best-of-10
replan at B = 1 runs the U-Net on 10 rows of length 4-16 with 32-256 channels, and there oneDNN's
per-call cost dominates: one call of the shipped U-Net at batch 10 took 4.6 ms, 98 MFLOP at 21
GFLOP/s on one core (``benchmarks/bench_unet_backends.py``). The same convolution written as one
GEMM (im2col: every output position's window of k inputs is a row, and the kernel a matrix) runs
the same multiply-adds through the BLAS.

Conv1d, stride s, padding p, kernel w (C_out, C_in, k), input x (B, C_in, L)::

    y[b, o, t] = bias[o] + sum_{c, j} w[o, c, j] xp[b, c, s t + j],   xp = x zero-padded by p each side
    im2col:  X[(b, t), (j, c)] = xp[b, c, s t + j],  W[(j, c), o] = w[o, c, j],  y = X W + bias

ConvTranspose1d, stride s, padding p, kernel w (C_in, C_out, k) with k a multiple of s (k = q s)::

    y_full[b, o, s i + j] += sum_c x[b, c, i] w[c, o, j]     (then y = y_full[p : p + L_out] + bias)
    one product Z = x^T W (B, L, k C_out); tap j = a s + r lands at position (i + a) s + r, so
    y_full (viewed (B, L + q - 1, s, C_out)) is the sum over a of Z's a-th group shifted by a.

aten's fused ``mish`` kernel is slower on a CPU than the three operations it fuses (20 against 12 us
for 5,120 values, one thread), at every batch size. The arithmetic and its order differ from
oneDNN's and aten's, so outputs agree to float rounding (about 1e-6 here), not bit for bit. At large
batches oneDNN's convolution is the faster one: the policy's traced U-Net (``inference_backend:
trace``) runs the matrix-product copy up to ``SMALL_BATCH_ROWS`` rows and the other above.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn
from torch.nn import functional

# Up to this many rows the matrix-product convolutions are the faster ones on a CPU (one thread, the
# shipped U-Net, both copies with SoftplusMish: 1.7x faster at 10 rows, 1.04x at 60, level at 80).
SMALL_BATCH_ROWS = 64


class Im2colConv1d(nn.Module):
    """``nn.Conv1d`` (groups 1, dilation 1, zero padding) as one matrix product (module docstring)."""

    def __init__(self, conv: nn.Conv1d):
        super().__init__()
        if not supports_conv1d(conv):
            raise ValueError(f"Im2colConv1d needs groups 1, dilation 1 and zero padding, got {conv}")
        w = conv.weight.detach()
        self.kernel, self.stride, self.padding = conv.kernel_size[0], conv.stride[0], conv.padding[0]
        # (k C_in, C_out), rows ordered (tap, channel) as the unfolded windows below
        self.register_buffer("weight", w.permute(2, 1, 0).reshape(-1, w.shape[0]).contiguous())
        bias = conv.bias.detach().clone() if conv.bias is not None else torch.zeros(w.shape[0])
        self.register_buffer("bias", bias)

    def forward(self, x: Tensor) -> Tensor:
        B = x.shape[0]
        # padded channels-last first: the windows' channels are then adjacent in memory, so gathering
        # them into rows copies runs of C_in values (7 % faster at 10 rows than padding channels-first)
        padded = functional.pad(x.transpose(1, 2), (0, 0, self.padding, self.padding)).contiguous()
        windows = padded.unfold(1, self.kernel, self.stride)
        length = windows.shape[1]  # (B, L_out, C_in, k)
        rows = windows.transpose(2, 3).reshape(B * length, -1)
        return torch.addmm(self.bias, rows, self.weight).view(B, length, -1).transpose(1, 2)


class SoftplusMish(nn.Module):
    """``nn.Mish`` as x tanh(softplus(x)): the same function, and on a CPU faster than aten's fused
    ``mish`` at these sizes (12 against 20 us for 5,120 values, one thread)."""

    def forward(self, x: Tensor) -> Tensor:
        return x * torch.tanh(functional.softplus(x))


class MatmulConvTranspose1d(nn.Module):
    """``nn.ConvTranspose1d`` (groups 1, dilation 1, kernel a multiple of the stride, no output
    padding) as one matrix product and q shifted sums (module docstring)."""

    def __init__(self, conv: nn.ConvTranspose1d):
        super().__init__()
        if not supports_conv_transpose1d(conv):
            raise ValueError(
                "MatmulConvTranspose1d needs groups 1, dilation 1, no output padding and a kernel that is a "
                f"multiple of the stride, got {conv}"
            )
        w = conv.weight.detach()  # (C_in, C_out, k)
        self.kernel, self.stride, self.padding = conv.kernel_size[0], conv.stride[0], conv.padding[0]
        self.out_channels = w.shape[1]
        # (C_in, k C_out), columns ordered (tap, channel)
        self.register_buffer("weight", w.permute(0, 2, 1).reshape(w.shape[0], -1).contiguous())
        bias = conv.bias.detach().clone() if conv.bias is not None else torch.zeros(w.shape[1])
        self.register_buffer("bias", bias)

    def forward(self, x: Tensor) -> Tensor:
        B, _, L = x.shape
        s, q, c = self.stride, self.kernel // self.stride, self.out_channels
        z = torch.matmul(x.transpose(1, 2), self.weight).view(B, L, q, s, c)
        full = functional.pad(z[:, :, 0], (0, 0, 0, 0, 0, q - 1))  # (B, L + q - 1, s, C_out)
        for a in range(1, q):
            full = full + functional.pad(z[:, :, a], (0, 0, 0, 0, a, q - 1 - a))
        length = (L - 1) * s + self.kernel - 2 * self.padding
        y = full.reshape(B, (L + q - 1) * s, c)[:, self.padding : self.padding + length]
        return (y + self.bias).transpose(1, 2)


def supports_conv1d(conv: nn.Module) -> bool:
    return (
        type(conv) is nn.Conv1d
        and conv.groups == 1
        and conv.dilation == (1,)
        and conv.padding_mode == "zeros"
        and isinstance(conv.padding, tuple)
    )


def supports_conv_transpose1d(conv: nn.Module) -> bool:
    return (
        type(conv) is nn.ConvTranspose1d
        and conv.groups == 1
        and conv.dilation == (1,)
        and conv.output_padding == (0,)
        and conv.kernel_size[0] % conv.stride[0] == 0
    )


def inference_copy(module: nn.Module, matmul_convolutions: bool) -> nn.Module:
    """A deep copy of ``module`` in eval mode whose ``Mish`` layers run as ``SoftplusMish`` and, with
    ``matmul_convolutions``, whose supported ``Conv1d`` and ``ConvTranspose1d`` layers run as matrix
    products (the weights are copied: later changes to ``module`` do not reach it)."""
    out = copy.deepcopy(module).eval()
    for parent in list(out.modules()):
        for name, child in parent.named_children():
            if type(child) is nn.Mish:
                setattr(parent, name, SoftplusMish())
            elif matmul_convolutions and supports_conv1d(child):
                setattr(parent, name, Im2colConv1d(child))
            elif matmul_convolutions and supports_conv_transpose1d(child):
                setattr(parent, name, MatmulConvTranspose1d(child))
    return out
