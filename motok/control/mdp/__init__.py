"""MDP terms: small pure functions on ``(N, ...)`` arrays that tasks compose (observations,
rewards, terminations, resets, action maps). None holds state; tasks own theirs."""
