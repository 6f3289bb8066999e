"""What a learned controller is: its config (``config``), its controller-side observation
features and action map (``wrappers``), the rest-anchored SB3 policy (``anchor``), loading a
trained run as a controller (``policies``), the compiled deployed path (``inference``) and the
run folder (``runs``). Needs the ``train`` extra (stable-baselines3, torch)."""
