"""The ROS-free rules of kvark_ros, in two parts by when they run, over a shared base.

- ``core.estimation``: live estimation, what the ROS node loads (and ``kvark replay`` runs offline);
- ``core.learning``: what ``kvark train`` and ``kvark diagnose`` add on top of it;
- this package's own modules, read by both: the key table (``config_schema``), the validated config (``config``),
  the observer catalog (``observer_catalog``) and atomic files (``files``).

``core`` imports nothing of ``io``, ``tools``, ``sim``, ``gap`` or ``ros``, and ``core.estimation`` nothing of
``core.learning`` (``test/test_architecture.py``).
"""
