"""Diagnostics of the science, read off finished runs' folders (never written to): questions a
result raises, answered on the runs themselves rather than timed like `benchmarks/`. Each is a
module run as `python -m experiments.diagnostics.<name>`:

- `distinguishability`: are the skill rule's queries easier for a noisy teacher to tell apart
  than disagreement's, on one agent?
- `skill_choice`: does R_theta's z_task pick a skill the S-EPOA policy does well with, against
  random skills?
- `reward_crosscheck`: is a low score the reward model's fault or the policy's? Every run's
  reward model judges every run's policy.
- `run_copy`: a run resumed from a copy of its checkpoint, which the others act with.
"""
