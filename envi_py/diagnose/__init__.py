"""Where the sim-to-real gap lies, which unmodelled effect causes it, how far it shrinks once added.

``residuals`` one-step prediction errors on real windows, every state channel; ``effects`` the
candidate effects, each a statistical signature in the residuals plus the model change that adds
it, tried on every state (or action) it can act on; ``gap`` where the closed-loop gap lies (the
system's goals against the project's fair floor, horizon, region, coverage); ``shrink`` retrains with an effect and
re-verifies on confirmation logs; ``report`` writes what a person reads; ``validate`` scores the
whole diagnosis on twin data whose effect was withheld.
"""
