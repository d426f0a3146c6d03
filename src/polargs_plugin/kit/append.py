"""Appending Gaussians to a trainer: raw-parameter conversions and one row-edit helper.

The common layout of 3DGS trainers is a dict of raw parameters (one ``nn.Parameter`` per name)
optimised by torch Adam, either one optimizer with one param group per name (graphdeco, GOF,
PGSR, the reference backend; each group carries ``"name"``) or one optimizer per name (gsplat).
:func:`edit_rows` replaces the parameters and keeps each optimizer's state aligned with the
rows (the pattern of gsplat's strategy ops); :func:`append_rows` is its most common use.

Raw parameters (:data:`RAW_NAMES`; each adapter maps its own names onto these):

==================  ===============  =============================================
name                shape            activation
==================  ===============  =============================================
``means``           (N, 3)           none (world positions)
``sh_dc``           (N, 1, 3)        SH DC, ``rgb = SH_C0 * dc + 0.5``
``sh_rest``         (N, K - 1, 3)    higher SH bands, K = (degree + 1) ** 2
``opacity_logits``  (N,)             sigmoid
``log_scales``      (N, 3)           exp
``quats``           (N, 4)           wxyz, normalised when activated
==================  ===============  =============================================
"""

from __future__ import annotations

from typing import Callable, Mapping, MutableMapping

import torch
from torch import Tensor, nn

from polargs_plugin.geometry import rgb_to_sh, sh_to_rgb
from polargs_plugin.types import GaussianState, NewGaussians

__all__ = [
    "RAW_NAMES",
    "logit",
    "raw_from_new",
    "new_from_raw",
    "state_from_raw",
    "edit_rows",
    "append_rows",
    "pad_rows",
]

RAW_NAMES = ("means", "sh_dc", "sh_rest", "opacity_logits", "log_scales", "quats")

Optimizers = torch.optim.Optimizer | Mapping[str, torch.optim.Optimizer]
"""One optimizer whose param groups carry ``"name"``, or one optimizer per parameter name."""

def logit(p: Tensor, eps: float = 1e-6) -> Tensor:
    """Inverse sigmoid, with ``p`` clamped to [eps, 1 - eps] so the result is finite."""
    p = p.clamp(eps, 1 - eps)
    return torch.log(p / (1 - p))


def raw_from_new(new: NewGaussians, sh_rest_coeffs: int, *, like: Tensor | None = None) -> dict[str, Tensor]:
    """Raw parameter rows (:data:`RAW_NAMES`) of Gaussians to append.

    Args:
        new: activated Gaussians (e.g. from ``PolarHooks.densify``).
        sh_rest_coeffs: K - 1, the number of higher SH coefficients of the model (zeros here).
        like: a tensor whose device and dtype the rows take (default: ``new.means``).

    Returns:
        ``{name: (M, ...) tensor}``: SH DC from the colours (clamped to [0, 1]), zero higher bands,
        logit opacities (finite), log scales, unit quaternions.
    """
    like = new.means if like is None else like
    m = len(new)

    def cast(t: Tensor, *shape: int) -> Tensor:
        return t.detach().to(device=like.device, dtype=like.dtype).reshape(m, *shape)

    return {
        "means": cast(new.means, 3),
        "sh_dc": rgb_to_sh(cast(new.colors, 3).clamp(0, 1)).unsqueeze(1),
        "sh_rest": like.new_zeros((m, sh_rest_coeffs, 3)),
        "opacity_logits": logit(cast(new.opacities)),
        "log_scales": torch.log(cast(new.scales, 3).clamp_min(1e-12)),
        "quats": nn.functional.normalize(cast(new.quats, 4), dim=-1),
    }


def new_from_raw(raw: Mapping[str, Tensor]) -> NewGaussians:
    """Activated Gaussians from raw rows (inverse of :func:`raw_from_new` for the DC colour)."""
    return NewGaussians(
        means=raw["means"],
        quats=nn.functional.normalize(raw["quats"], dim=-1),
        scales=torch.exp(raw["log_scales"]),
        colors=sh_to_rgb(raw["sh_dc"].reshape(-1, 3)).clamp(0, 1),
        opacities=torch.sigmoid(raw["opacity_logits"].reshape(-1)),
    )


def state_from_raw(raw: Mapping[str, Tensor]) -> GaussianState:
    """The hooks' :class:`GaussianState` (activated, autograd-connected) of raw parameters.

    ``raw`` needs ``means``, ``quats``, ``log_scales`` and ``opacity_logits`` ((N,) or (N, 1)).
    """
    return GaussianState(
        means=raw["means"],
        quats=nn.functional.normalize(raw["quats"], dim=-1),
        scales=torch.exp(raw["log_scales"]),
        opacities=torch.sigmoid(raw["opacity_logits"].reshape(-1)),
    )


def _find_group(optimizers: Optimizers, name: str) -> tuple[torch.optim.Optimizer, dict]:
    if isinstance(optimizers, Mapping):
        optimizer = optimizers[name]
        if len(optimizer.param_groups) != 1:
            raise ValueError(f"optimizer '{name}' must have exactly one param group")
        return optimizer, optimizer.param_groups[0]
    for group in optimizers.param_groups:
        if group.get("name") == name:
            return optimizers, group
    raise KeyError(f"no optimizer param group named '{name}'")


def edit_rows(
    params: MutableMapping[str, Tensor],
    optimizers: Optimizers,
    param_fn: Callable[[str, Tensor], Tensor],
    state_fn: Callable[[str, Tensor], Tensor],
    names: tuple[str, ...] | None = None,
) -> dict[str, nn.Parameter]:
    """Replace parameters row-wise and keep the optimizer state aligned (in place).

    For each name, the parameter becomes ``nn.Parameter(param_fn(name, old))`` in ``params`` and in
    its optimizer group, and every per-row optimizer state tensor (Adam's ``exp_avg``,
    ``exp_avg_sq``; anything whose first dimension is N) becomes ``state_fn(name, old_state)``.
    Scalar state (Adam's ``step``) is kept.

    Args:
        params: name -> parameter (a dict or ``nn.ParameterDict``); updated in place.
        optimizers: one optimizer whose groups carry ``"name"``, or a dict name -> optimizer.
        param_fn: ``(name, old detached tensor) -> new tensor``.
        state_fn: ``(name, old state tensor) -> new state tensor``.
        names: which parameters to edit (default: all of ``params``).

    Returns:
        The new parameters by name (also written into ``params``).
    """
    replaced: dict[str, nn.Parameter] = {}
    for name in names if names is not None else tuple(params.keys()):
        optimizer, group = _find_group(optimizers, name)
        old = params[name]
        if len(group["params"]) != 1 or group["params"][0] is not old:
            raise ValueError(f"param group '{name}' does not hold exactly the parameter params['{name}']")
        new = nn.Parameter(param_fn(name, old.detach()).contiguous(), requires_grad=old.requires_grad)
        state = optimizer.state.pop(old, None)
        if state:
            for key, value in state.items():
                if isinstance(value, Tensor) and value.dim() > 0 and value.shape[0] == old.shape[0]:
                    state[key] = state_fn(name, value).contiguous()
            optimizer.state[new] = state
        group["params"][0] = new
        params[name] = new
        replaced[name] = new
    return replaced


def pad_rows(tensor: Tensor, m: int) -> Tensor:
    """``tensor`` with ``m`` zero rows appended along dimension 0."""
    return torch.cat([tensor, tensor.new_zeros((m, *tensor.shape[1:]))], dim=0)


def append_rows(
    params: MutableMapping[str, Tensor],
    optimizers: Optimizers,
    rows: Mapping[str, Tensor],
    state: MutableMapping[str, Tensor | None] | None = None,
) -> dict[str, nn.Parameter]:
    """Append rows to every parameter: zero Adam moments for them, the step counter kept.

    Args:
        params: name -> parameter; every name needs a row tensor in ``rows``.
        optimizers: as :func:`edit_rows`.
        rows: name -> (M, ...) new raw rows (cast to the parameter's device and dtype).
        state: optional per-Gaussian statistics (e.g. gradient accumulators, gsplat strategy
            state); each tensor whose first dimension is N gets M zero rows, in place. ``None``
            values and other entries are left alone. Pass per-Gaussian entries only: a matrix
            whose first dimension happens to equal N (MCMC's ``binoms``) would be padded too.

    Returns:
        The new parameters by name (also written into ``params``).
    """
    missing = set(params.keys()) - set(rows)
    if missing:
        raise KeyError(f"append_rows: no new rows for {sorted(missing)}")
    first = next(iter(params.values()))
    n = first.shape[0]
    m = int(next(iter(rows.values())).shape[0])
    for name, value in rows.items():
        if name in params and tuple(value.shape[1:]) != tuple(params[name].shape[1:]):
            raise ValueError(
                f"append_rows: rows['{name}'] has shape {tuple(value.shape)}, expected (M, "
                f"{', '.join(map(str, params[name].shape[1:]))})"
            )
        if value.shape[0] != m:
            raise ValueError(f"append_rows: rows['{name}'] has {value.shape[0]} rows, others {m}")
    replaced = edit_rows(
        params,
        optimizers,
        lambda name, old: torch.cat([old, rows[name].detach().to(old)], dim=0),
        lambda name, value: pad_rows(value, m),
    )
    if state is not None:
        for key, value in state.items():
            if isinstance(value, Tensor) and value.dim() > 0 and value.shape[0] == n:
                state[key] = pad_rows(value, m)
    return replaced
