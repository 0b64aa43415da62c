"""Learning: what ``kvark train`` and ``kvark diagnose`` load on top of ``core.estimation``.

The training pipeline (residual models, the per-joint choice of second inputs, tuning by covariance matching), the
static friction band's identification and the interval factors read from contact-free recordings. The node never
imports this package.
"""
