"""telebot-router: a zenoh router with TLS, client certificates and access control.

``certs`` makes the CA and the certificates (``cryptography``); ``acl`` is sans-IO: it
turns the names that hold certificates into zenoh JSON5 configs for the router and its
clients. The router itself is plain zenoh (``apps/router_cli.py`` opens a zenoh-python
session in router mode; ``zenohd -c`` with the same config works the same).
"""
