"""Sensor models: every measurement becomes world-frame rays in metres (design 2)."""
