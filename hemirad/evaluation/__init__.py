"""Checking a solve against independent answers: path-traced references (Mitsuba, an
optional extra), image metrics, and the geometric penumbra finder the figures use."""
