"""Text to physics in a closed loop: the GPT re-plans from where the simulated character is
(``loop``: the command; ``replan``: encode, continue, anchor; ``timeline``: the token-grid schedule
and prompt timelines; ``files``: what it writes)."""
