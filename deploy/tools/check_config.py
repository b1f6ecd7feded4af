#!/usr/bin/env python3
"""Check the scone TOML embedded in the Kubernetes ConfigMaps and the keys file example.

TOML: parses, and uses only settings the server knows (the server rejects unknown keys: `deny_unknown_fields`).
KNOWN mirrors src/settings.rs and the structs it embeds (model: EmbedderSettings, store: StoreSettings) as of this
writing; the whole-section entries (limits, extractor, store.index ...) are not checked further.
Keys file: every non-comment line is `write <key>` or `read <key>`, like the server's parser.
Usage: check_config.py CONFIGMAP.yaml... [--keys KEYSFILE]"""
import sys
import tomllib

import yaml

KNOWN = {
    "server": {"grpc_addr", "http_addr", "request_timeout_ms", "shutdown_grace_ms", "max_request_bytes",
               "max_map_bytes", "max_connections", "header_read_timeout_ms", "body_read_timeout_ms",
               "idle_timeout_ms", "tcp_keepalive_ms", "grpc_keepalive_interval_ms", "grpc_keepalive_timeout_ms",
               "max_concurrent_streams", "allowed_origins"},
    "auth": {"write_keys", "read_keys", "keys_file", "allow_anonymous"},
    "workers": {"threads", "queue", "refusal_hold_ms"},
    "relative_pose": None,
    "model": {"model", "runtime_library", "sessions", "intra_threads", "spinning"},
    "store": {"data_dir", "compact_every", "index", "build", "localize", "backend", "cache"},
    "limits": None,
    "extractor": None,
}


def check_toml(label, text):
    errors = []
    settings = tomllib.loads(text)
    for section, values in settings.items():
        if section not in KNOWN:
            errors.append(f"unknown section [{section}]")
            continue
        if KNOWN[section] is None:
            continue
        for key in values:
            if key not in KNOWN[section]:
                errors.append(f"unknown key {section}.{key}")
    print(f"{label}: {'OK' if not errors else 'ERROR ' + '; '.join(errors)} ({', '.join(settings)})")
    return not errors


def check_keys(label, text):
    ok = True
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2 or parts[0] not in ("write", "read"):
            print(f"{label}:{n}: ERROR not `write <key>` / `read <key>`")
            ok = False
    print(f"{label}: {'OK' if ok else 'ERROR'} (keys file format)")
    return ok


def main(argv):
    ok = True
    if "--keys" in argv:
        i = argv.index("--keys")
        with open(argv[i + 1], encoding="utf-8") as f:
            ok &= check_keys(argv[i + 1], f.read())
        argv = argv[:i] + argv[i + 2:]
    for path in argv:
        with open(path, encoding="utf-8") as f:
            for doc in yaml.safe_load_all(f):
                if doc and doc.get("kind") == "ConfigMap":
                    for name, text in doc.get("data", {}).items():
                        if name.endswith(".toml"):
                            ok &= check_toml(f"{path} [{doc['metadata']['name']}/{name}]", text)
                if doc and doc.get("kind") == "Secret":
                    for name, text in doc.get("stringData", {}).items():
                        ok &= check_keys(f"{path} [{doc['metadata']['name']}/{name}]", text)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
