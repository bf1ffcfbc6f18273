"""Sensor models: every measurement becomes world-frame rays in metres (docs/method.md 2)."""
