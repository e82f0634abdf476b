"""Hostile-input campaign (issue 15): seeded, bounded generators of what an attacker or a buggy
client sends (mutated cell files, hostile HTTP requests), and the tests that throw them at every
face. The generators are plain functions of a seed and a count, reusable by further campaigns."""
