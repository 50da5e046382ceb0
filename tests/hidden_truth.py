"""The hidden ground truth the server and web tests push with their pairs: values no other field
has, so a test can look for them in a response or a page (where a labeller must never see them)
and find them in an operator's export. Tests take it as the `secret_returns` fixture; builders
that push pairs import it from here."""

from __future__ import annotations

SECRET_RETURNS = {
    "first_segment_return": 987.125,
    "second_segment_return": -654.375,
    "first_trajectory_return": 4321.5,
    "second_trajectory_return": -8765.25,
    "model_p": 0.123456,
    "score": 7.654321,
}
