"""Where the sim-to-real gap lies, which unmodelled effect causes it, how far it shrinks once added.

In stages: ``data_quality`` first (pauses in the time stamps, repeated or frozen readings, readings
outside the declared ranges, sessions that differ as a block); ``stages`` then asks whether the
model's class is wrong (a deterministic model of a world whose runs vary) and refits it; the rest is
of the refit. ``residuals`` one-step prediction errors on real windows, every state channel;
``effects`` the candidate effects, each a statistical signature in the residuals plus the model
change that adds it, tried on every state (or action) it can act on; ``gap`` where the closed-loop
gap lies (the system's goals against the project's fair floor, horizon, region, coverage) and
whether there is one at all; ``shrink`` retrains with an effect and re-verifies on confirmation
logs; ``report`` writes what a person reads; ``validate`` scores the whole diagnosis on twin data
whose effect was withheld.
"""
