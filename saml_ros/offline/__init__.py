"""Offline training: the paper's datasets, Sufficiently / Uniformly Accurate training, evaluation, figures.

* :mod:`.pipelines`: generate datasets, train many seeds as one ensemble, evaluate per region;
* :mod:`.cli`: ``ros2 run saml_ros train`` (from generated data or from bags);
* :mod:`.plots`: training curves, held-out error comparisons, the double-integrator error map.
"""
