"""Sender-side encoding, REST and Zenoh clients for bb-align."""
