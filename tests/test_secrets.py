"""Secrets stay secret: the API token and storage credentials never reach config.yaml, checkpoints,
the storage's copies, logs, metrics or error messages."""

from pathlib import Path

import pytest

from covers_dist.api import resolve_token
from covers_dist.config import ConfigError, config_to_dict, load_config
from covers_dist.runtime.driver import Trainer
from covers_dist.storage import Storage, StorageError, redact_uri, uri_credentials

from test_runtime_serial import tiny_cfg

TOKEN = "tok-5f1c9e2a-never-saved"


def files_holding(root: Path, secret: str) -> list[str]:
    """Every file under ``root`` whose bytes contain ``secret`` (gzip-rotated logs included)."""
    import gzip

    hits = []
    for p in root.rglob("*"):
        if not p.is_file():
            continue
        data = p.read_bytes()
        if p.suffix == ".gz":
            data += gzip.decompress(data)
        if secret.encode() in data:
            hits.append(str(p.relative_to(root)))
    return hits


def test_a_token_given_on_the_command_line_is_used_but_never_written(tmp_path):
    store = tmp_path / "store"
    cfg = tiny_cfg(tmp_path / "run", "runtime.total_env_steps=800", f"runtime.storage={store}", f"api.token={TOKEN}")
    assert resolve_token(cfg) == TOKEN and cfg.api.token == TOKEN
    lines: list[str] = []
    trainer = Trainer(cfg, log=lines.append)
    try:
        assert trainer.run()["status"] == "finished"
    finally:
        trainer.close()
    assert config_to_dict(cfg)["api"]["token"] is None
    assert (tmp_path / "run" / "checkpoints").is_dir() and any(store.rglob("config.yaml"))
    assert files_holding(tmp_path, TOKEN) == []  # run directory, checkpoints, storage copies, logs, metrics
    assert not any(TOKEN in line for line in lines)


def test_the_token_comes_from_a_file_or_the_environment_and_a_bad_file_is_named(tmp_path, monkeypatch):
    monkeypatch.delenv("COVERS_API_TOKEN", raising=False)
    secret_file = tmp_path / "token"
    secret_file.write_text(f"{TOKEN}\n")
    assert resolve_token(load_config(None, [f"api.token_file={secret_file}"])) == TOKEN
    monkeypatch.setenv("COVERS_API_TOKEN", "from-env")
    assert resolve_token(load_config(None)) == "from-env"
    with pytest.raises(ConfigError, match=r"api.token_file=.*missing.* cannot be read \(FileNotFoundError\)"):
        resolve_token(load_config(None, [f"api.token_file={tmp_path / 'missing'}"]))
    (tmp_path / "empty").write_text("\n")
    with pytest.raises(ConfigError, match="holds no token"):
        resolve_token(load_config(None, [f"api.token_file={tmp_path / 'empty'}"]))


def test_storage_credentials_in_a_uri_are_refused_by_the_config_and_never_printed():
    for uri in ("s3://AKIAKEY:SECRETVALUE@bucket/run", "s3://bucket/run?access_key=AKIAKEY&secret_key=SECRETVALUE"):
        with pytest.raises(ConfigError, match="carries credentials") as err:
            load_config(None, [f"runtime.storage={uri}"])
        assert "SECRETVALUE" not in str(err.value) and "AKIAKEY" not in str(err.value)
        assert uri_credentials(uri)
        assert "SECRETVALUE" not in redact_uri(uri) and "AKIAKEY" not in redact_uri(uri)
    assert uri_credentials("s3://bucket/run?endpoint_override=127.0.0.1:9000&scheme=http") == []
    kept = "s3://bucket/run?endpoint_override=127.0.0.1:9000&scheme=http"
    assert redact_uri(kept) == kept


def test_a_storage_opened_with_credentials_redacts_them_in_its_repr_and_errors():
    uri = "s3://AKIAKEY:SECRETVALUE@bucket/run?endpoint_override=127.0.0.1:1&scheme=http"
    retries: list[str] = []
    store = Storage(uri, retry_s=8.0, log=retries.append)  # a closed port on loopback: every request fails
    shown = [repr(store), store.describe("k")]
    with pytest.raises(StorageError, match="kept failing for 8 s") as err:
        store.read_bytes("k")
    assert retries and all("retry" in line for line in retries)
    shown += [str(err.value), *retries]
    with pytest.raises(StorageError) as bad:
        Storage("s3://AKIAKEY:SECRETVALUE@bucket/run?secret_key=SECRETVALUE&bogus_option=1")
    shown.append(str(bad.value))
    for text in shown:
        assert "SECRETVALUE" not in text and "AKIAKEY" not in text, text
