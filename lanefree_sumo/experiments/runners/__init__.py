"""What runs: training (SB3's loop and the batch, :mod:`.train`, :mod:`.batch`), evaluation, rollouts, replay, the
background-traffic simulation and the mixed-autonomy ring — each writes its output through :mod:`..storage`."""
