"""The trainer: SAC, the preference reward model, query selection, scripted teachers and the
preference-learning loop. It never imports the server (see docs/ARCHITECTURE.md)."""
