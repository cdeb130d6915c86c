"""Stages 2 and 3: the feedback model Fhat, the HF policy and guided PPO."""
