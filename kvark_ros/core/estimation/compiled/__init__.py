"""The compiled step: every per-sample computation of ``Estimator.step`` but the pinocchio passes, as numba kernels.

One ``Estimator.step`` of the default filter cost ~1.04 M instructions in numpy, most of them numpy's per-call
overhead on 6- and 7-element arrays; compiled it costs a few per cent of that. Modules:

- ``layouts``: the entries of the packed arrays the kernels take, each declared once;
- ``inputs``: the checks of one input sample;
- ``residual``: the KMP residual's prediction and the augmentation's joint torque at one sample;
- ``kvark_filter``: the K-VARK momentum filter's step on its packed state;
- ``wrench``: the wrench and its covariance through the damped pseudo-inverse, weak directions included;
- ``post``: ``estimate_step``, one call per sample: p and u, the models, the filter, the post-step of every observer;
- ``step``: ``CompiledStep``, the Python side: buffers allocated once, the observer's hand-over, the calls;
- ``jit``: the decorator and the rule that keeps numba's on-disk cache exact (``PINS``).

The numpy references are test oracles (test/core/reference_filter.py, test/core/reference_estimator.py); the kernels
differ from them by rounding only (test/core/test_compiled_step_matches_reference.py).
"""
