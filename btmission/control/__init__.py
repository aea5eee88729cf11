"""Reactive navigation: NMPC tracking, APF avoidance, DPHR heading and COMPRA exploration."""
