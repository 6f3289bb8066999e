"""Evaluation: the one episode runner (``episodes``; its metric window is
``mpa_gym.analysis.simulate.metric_window``, shared with ``mpa-gym simulate``), the report
(``evaluate``), the robustness sweep and no-harm audit (``robustness``), intervals over seeds
(``seeds``)."""
