"""Screens of their own over the main one: help, replay against a server, and
the bisect prompts (the first violation of a rule, where two connections part)."""
