"""Test support: scenes, fixtures, stand-ins and helpers shared by the test modules (no tests here)."""
