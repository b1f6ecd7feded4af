#!/usr/bin/env python3
"""Check Envoy bootstrap YAML files against Envoy's v3 API (the protobuf messages of the PyPI package
envoy-data-plane): every field name, enum value and nested type, including the messages inside `typed_config`
(`@type`). This is not `envoy --mode validate`: it does not apply Envoy's validation rules (required fields,
ranges) nor its semantic checks. Usage: check_envoy.py FILE...  (exit 1 on the first error of each file)."""
import importlib
import re
import sys

import yaml

PREFIX = "type.googleapis.com/"


def register_any_types(node):
    """Import the module of every `@type` so that betterproto2 can unpack the Any."""
    if isinstance(node, dict):
        url = node.get("@type")
        if isinstance(url, str) and url.startswith(PREFIX):
            package = url[len(PREFIX):].rsplit(".", 1)[0]
            importlib.import_module("envoy_data_plane." + package)
        for value in node.values():
            register_any_types(value)
    elif isinstance(node, list):
        for value in node:
            register_any_types(value)


def keep_snake_case_keys():
    """betterproto2 re-cases every key with safe_snake_case, which turns `consecutive_5xx` (OutlierDetection) into
    `consecutive_5_xx`, a field that does not exist. Keys already in snake_case (as Envoy's YAML is) stay as they are."""
    import betterproto2

    original = betterproto2.safe_snake_case

    def snake(key):
        return key if re.fullmatch(r"[a-z][a-z0-9_]*", key) else original(key)

    betterproto2.safe_snake_case = snake


def main(paths):
    keep_snake_case_keys()
    from envoy_data_plane.envoy.config.bootstrap.v3 import Bootstrap

    failed = False
    for path in paths:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
        try:
            register_any_types(doc)
            bootstrap = Bootstrap.from_dict(doc)
            listeners = bootstrap.static_resources.listeners
            clusters = bootstrap.static_resources.clusters
            # Round trip: the parsed message must serialise back.
            bytes(bootstrap)
            print(f"{path}: OK ({len(listeners)} listeners, {len(clusters)} clusters)")
        except Exception as e:  # noqa: BLE001 - report any parse error with its file
            failed = True
            print(f"{path}: ERROR {type(e).__name__}: {e}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
