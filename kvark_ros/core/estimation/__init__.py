"""Live estimation: everything the ROS node loads, and the same code ``kvark replay`` runs offline.

The Estimator and its compiled step, the observers, the robot model with its augmentation, the residual models
(their prediction; fitting code loads only when a model is fitted), contact and collision tests, tare, pairing of
joint states with commands, the static friction band and interval factors a trained model carries, and model
directories. Nothing here imports ``core.learning`` (``test/test_architecture.py``).
"""
