"""Evaluation: the one episode runner and metric window (``episodes``), the report
(``evaluate``), the robustness sweep and no-harm audit (``robustness``), intervals over seeds
(``seeds``)."""
