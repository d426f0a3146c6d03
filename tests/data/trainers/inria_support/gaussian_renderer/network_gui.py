"""Placeholder viewer connection: never connected."""

conn = None


def init(ip, port):
    return None


def try_connect():
    return None


def receive():
    return None
