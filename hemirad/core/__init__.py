"""The bottom layer: errors, tensor idioms, devices, colour, timing and process settings.

Everything else in hemirad may import from here; nothing here imports from the rest.
"""
