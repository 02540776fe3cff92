"""Tasks: what the policy is asked to do, composed from ``motok.control.mdp`` terms. A task owns
its episode state (reference clip and frame, targets, step counts) and its random generator."""
