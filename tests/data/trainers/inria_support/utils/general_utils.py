"""Placeholder helpers (upstream names)."""

import math


def get_expon_lr_func(lr_init, lr_final, max_steps=1000000, **_):
    """Log-linear interpolation from lr_init to lr_final over max_steps (0 stays 0)."""
    def rate(step):
        if lr_init == 0.0 and lr_final == 0.0:
            return 0.0
        t = min(max(step / max_steps, 0.0), 1.0)
        return math.exp(math.log(lr_init) * (1 - t) + math.log(max(lr_final, 1e-12)) * t)
    return rate
