"""The verbs of `magcal`, one module each where a verb is more than a call."""
