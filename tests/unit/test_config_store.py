"""``[registry] store`` and its keys: the URL, TLS files, prefix, lease, gateway id, advertise;
``open_store`` picks the store they name."""

from __future__ import annotations

from pathlib import Path

import pytest

from gateway.cli import main
from gateway.config import ConfigError, load_config, loads_config
from gateway.stores import EtcdStore, default_gateway_id, open_store, parse_store_url
from services.apps.registry.embedded import EmbeddedStore
from services.apps.registry.store import EMBEDDED, SharedStore


def test_the_store_is_embedded_by_default() -> None:
    config = loads_config("")
    section = config.registry
    assert (section.store, section.store_prefix, section.store_lease) == ("", "/propertyservice", 5.0)
    assert (section.gateway_id, section.advertise) == ("", "")
    store = open_store(config)
    assert isinstance(store, EmbeddedStore)
    assert (store.location, store.read_only, store.shared) == (EMBEDDED, "", False)


def test_an_etcd_store_is_read_with_its_keys(tmp_path: Path) -> None:
    for name in ("ca.pem", "gw.pem", "gw.key"):
        (tmp_path / "tls").mkdir(exist_ok=True)
        (tmp_path / "tls" / name).write_text("PEM")
    path = tmp_path / "gw.toml"
    path.write_text(
        """
        [registry]
        store = "etcds://10.0.0.1:2379,etcd-2.example:2379"
        store_ca = "tls/ca.pem"
        store_cert = "tls/gw.pem"
        store_key = "tls/gw.key"
        store_prefix = "/site/a/"
        store_lease = 3
        gateway_id = "gw-a"
        advertise = "10.0.0.5:50051"
        peer_ca = "tls/ca.pem"
        peer_cert = "tls/gw.pem"
        peer_key = "tls/gw.key"
        """
    )
    section = load_config(path).registry
    assert section.store == "etcds://10.0.0.1:2379,etcd-2.example:2379"
    assert section.store_ca == str(tmp_path / "tls" / "ca.pem")
    assert (section.store_cert, section.store_key) == (
        str(tmp_path / "tls/gw.pem"),
        str(tmp_path / "tls/gw.key"),
    )
    assert (section.store_prefix, section.store_lease) == ("/site/a", 3.0)
    assert (section.gateway_id, section.advertise) == ("gw-a", "10.0.0.5:50051")
    assert (section.peer_ca, section.peer_cert, section.peer_key) == tuple(
        str(tmp_path / "tls" / name) for name in ("ca.pem", "gw.pem", "gw.key")
    )


def test_open_store_makes_an_etcd_store_named_by_the_config() -> None:
    config = loads_config('[registry]\nstore = "etcd://127.0.0.1:2379"\nstore_lease = 2\n')
    store = open_store(config, listen="127.0.0.1:50123")
    assert isinstance(store, EtcdStore) and isinstance(store, SharedStore)
    assert store.location == "etcd://127.0.0.1:2379"
    assert store.gateway_id == default_gateway_id("127.0.0.1:50123")
    assert store.gateway_id.endswith("-50123")
    assert store.read_only.startswith("etcd at 127.0.0.1:2379 cannot be reached (not connected yet")
    named = open_store(loads_config('[registry]\nstore = "etcd://127.0.0.1:2379"\ngateway_id = "gw-7"\n'))
    assert isinstance(named, EtcdStore) and named.gateway_id == "gw-7"


def test_the_gateway_id_is_the_same_for_the_same_host_and_port() -> None:
    assert default_gateway_id("0.0.0.0:50051") == default_gateway_id("127.0.0.1:50051")
    assert default_gateway_id("127.0.0.1:50051") != default_gateway_id("127.0.0.1:50052")
    assert "/" not in default_gateway_id("[::1]:50051")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            'store = "redis://127.0.0.1:6379"',
            r"registry.store: unknown store scheme 'redis://'.*known: etcd://, etcds://",
        ),
        ('store = "127.0.0.1:2379"', "registry.store: expected a URL like 'etcd://127.0.0.1:2379'"),
        ('store = "etcd://"', "registry.store: name 1 to 16 endpoints"),
        ('store = "etcd://127.0.0.1"', "registry.store: expected host:port"),
        ('store = "etcd://127.0.0.1:2379,"', "registry.store: expected host:port"),
        ('store = "etcd://127.0.0.1:99999"', "registry.store: expected host:port"),
        ('store = "etcd://127.0.0.1:2379"\npersist = "reg.json"', "registry.persist: keeps the embedded"),
        (
            'store = "etcd://127.0.0.1:2379"\nstore_ca = "ca.pem"',
            "registry.store_ca: TLS files need .*etcds://",
        ),
        ('store_cert = "a.pem"', "registry.store_cert: TLS files need"),
        ('store = "etcds://127.0.0.1:2379"\nstore_ca = "nowhere.pem"', "registry.store_ca: no such file"),
        ('store = "etcds://127.0.0.1:2379"\nstore_cert = "c.pem"', "give both 'store_cert' and 'store_key'"),
        ('store_prefix = "propertyservice"', "registry.store_prefix: expected a folder of keys"),
        ('store_prefix = "/"', "registry.store_prefix: expected a folder of keys"),
        ("store_lease = 0.5", "registry.store_lease: must be from 1 to 3600 seconds"),
        ("store_lease = nan", "registry.store_lease: must be from 1 to 3600 seconds"),
        ('store_lease = "5s"', "registry.store_lease: expected a number"),
        ('gateway_id = "a/b"', "registry.gateway_id: 1 to 128 printable characters"),
        ('gateway_id = "a b"', "registry.gateway_id: 1 to 128 printable characters"),
        ('advertise = "somewhere"', "registry.advertise: expected host:port"),
        (
            'peer_ca = "ca.pem"',
            "registry.peer_ca: TLS files for the other gateways of a cluster need a store",
        ),
        ('store = "etcd://127.0.0.1:2379"\npeer_ca = "nowhere.pem"', "registry.peer_ca: no such file"),
        ('store = "etcd://127.0.0.1:2379"\npeer_key = "k.pem"', "give both 'peer_cert' and 'peer_key'"),
        ("store = 2379", "registry.store: expected a string"),
    ],
)
def test_bad_store_settings_are_refused_by_key(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        loads_config(f"[registry]\n{text}\n", "site.toml")


def test_check_config_names_every_bad_store_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[registry]\nstore = "consul://127.0.0.1:8500"\nstore_lease = 0\n')
    assert main(["check-config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "registry.store: unknown store scheme 'consul://'" in err
    assert "registry.store_lease: must be from 1 to 3600 seconds" in err


def test_store_urls_parse_into_endpoints() -> None:
    address = parse_store_url("etcd://127.0.0.1:2379, 127.0.0.1:22379")
    assert address.endpoints == ("127.0.0.1:2379", "127.0.0.1:22379") and not address.tls
    assert str(address) == "etcd://127.0.0.1:2379,127.0.0.1:22379"
    assert parse_store_url("etcds://[::1]:2379").tls
    with pytest.raises(ValueError, match="name 1 to 16 endpoints"):
        parse_store_url("etcd://" + ",".join(f"127.0.0.1:{2000 + n}" for n in range(17)))
