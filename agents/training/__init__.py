"""PPO training from an rl-zoo style config (``train``), several seeds in parallel
(``seeds``), Optuna studies of the config (``tune``) and of the classical baselines' gains
(``tune_baselines``)."""
