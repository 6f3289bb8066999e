"""Controllers behind SB3's ``predict(obs, state, episode_start)``: the classical baselines
(``ff``, ``pid``, ``mbfb``, ``afc``, ``rc``) and their gains files, the excitation for
identification, and the supervisor that runs a learned policy under run-time assurance. They
need the base install only (numpy, scipy, PyYAML), no learning library."""
