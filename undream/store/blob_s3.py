"""The S3 blob backend: blobs as objects ``<prefix>/<key>`` in a bucket of S3-compatible storage.

For farms whose machines share no folder (a Kubernetes cluster without a
ReadWriteMany volume): AWS S3, MinIO, Ceph RGW, ... through boto3. A PUT
replaces an object whole, so writes are atomic and idempotent. The endpoint,
region and keys come from the settings (:class:`undream.store.blobs.BlobOptions`,
filled at the edge from ``UNDREAM_S3_*`` or the usual ``AWS_*`` variables);
with no keys set, boto3's own chain (an instance role, a web identity) applies.
No message, log line or repr shows a key: the endpoint is shown redacted, the
secret never.
"""
from __future__ import annotations

import datetime as dt
import secrets
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from undream.errors import StoreError
from undream.redact import redact_text
from undream.store.blob_backends import BlobInfo, BlobMissing

if TYPE_CHECKING:
    from undream.store.blobs import BlobOptions

_BATCH = 1000  # keys per DeleteObjects request (S3's limit)
_MISSING = ("404", "NoSuchKey", "NotFound")


class S3Backend:
    """Blob bytes as objects of ``bucket`` under ``prefix`` (see the module docstring)."""

    def __init__(self, bucket: str, prefix: str, options: "BlobOptions") -> None:
        try:
            import boto3
            from botocore.config import Config
            from botocore.exceptions import BotoCoreError, ClientError
        except ModuleNotFoundError:
            raise StoreError("blob URL s3://: boto3 is not installed (pip install boto3)") from None
        self.bucket, self.prefix = bucket, prefix
        self._errors = (BotoCoreError, ClientError)  # what boto3 raises (imported with it, here)
        self._secret = options.s3_secret_access_key or ""
        endpoint = options.s3_endpoint_url or None
        at = f" at {redact_text(endpoint)}" if endpoint else ""
        self.where = f"S3 bucket 's3://{bucket}/{prefix}'{at}"
        session = boto3.session.Session(aws_access_key_id=options.s3_access_key_id or None,
                                        aws_secret_access_key=options.s3_secret_access_key or None,
                                        region_name=options.s3_region or None)
        config = Config(connect_timeout=10, read_timeout=120, retries={"max_attempts": 5, "mode": "standard"},
                        s3={"addressing_style": "path" if endpoint else "auto"})
        try:
            self.client = session.client("s3", endpoint_url=endpoint, config=config)
        except Exception as exc:  # botocore's errors for a bad endpoint or region: one line, no secret
            raise StoreError(f"{self.where}: cannot make an S3 client: {self._clean(exc)}") from None

    def __repr__(self) -> str:
        return f"S3Backend({self.where})"

    def _name(self, key: str) -> str:
        return f"{self.prefix}/{key}" if self.prefix else key

    def _key(self, name: str) -> str:
        return name[len(self.prefix) + 1:] if self.prefix else name

    def _clean(self, exc: BaseException) -> str:
        text = " ".join(str(exc).split())
        if self._secret:
            text = text.replace(self._secret, "***")
        return redact_text(text)

    def _fail(self, op: str, key: str, exc: BaseException) -> NoReturn:
        code = str(getattr(exc, "response", {}).get("Error", {}).get("Code", ""))
        if code in _MISSING:
            raise BlobMissing(key) from None
        hint = "; create the bucket first" if code == "NoSuchBucket" else ""
        raise StoreError(f"blob {key!r}: cannot {op} it in the {self.where}: {self._clean(exc)}{hint}") from None

    def _call(self, op: str, key: str, method: str, **kwargs: Any) -> Any:
        try:
            return getattr(self.client, method)(Bucket=self.bucket, **kwargs)
        except self._errors as exc:
            self._fail(op, key, exc)

    def write(self, key: str, data: bytes, durable: bool = True) -> None:  # S3 stores it when it answers
        self._call("write", key, "put_object", Key=self._name(key), Body=data)

    def write_file(self, key: str, src: Path) -> int:
        with open(src, "rb") as f:
            self._call("write", key, "put_object", Key=self._name(key), Body=f)
        return Path(src).stat().st_size

    def read(self, key: str) -> bytes:
        body = self._call("read", key, "get_object", Key=self._name(key))["Body"]
        try:
            return body.read()
        except self._errors as exc:
            self._fail("read", key, exc)

    def local_path(self, key: str) -> Path | None:
        return None

    def exists(self, key: str) -> bool:
        try:
            self._call("look up", key, "head_object", Key=self._name(key))
        except BlobMissing:
            return False
        return True

    def size(self, key: str) -> int:
        return int(self._call("look up", key, "head_object", Key=self._name(key))["ContentLength"])

    def listing(self, prefix: str) -> list[BlobInfo]:
        name = self._name(prefix)
        out = []
        try:
            for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=name):
                for obj in page.get("Contents", []):
                    if obj["Key"] == name or obj["Key"].startswith(name + "/"):
                        used = obj["LastModified"]
                        out.append(BlobInfo(self._key(obj["Key"]), int(obj["Size"]),
                                            used if used.tzinfo else used.replace(tzinfo=dt.timezone.utc)))
        except self._errors as exc:
            self._fail("list", prefix, exc)
        return out

    def touch(self, key: str) -> None:
        """Copy the object onto itself (S3 keeps no access time; this renews ``LastModified``)."""
        name = self._name(key)
        try:
            self._call("touch", key, "copy_object", Key=name, CopySource={"Bucket": self.bucket, "Key": name},
                       MetadataDirective="REPLACE")
        except BlobMissing:
            pass

    def delete_prefix(self, prefix: str) -> int:
        keys = [info.key for info in self.listing(prefix)]
        self.delete(keys)
        return len(keys)

    def delete(self, keys: list[str]) -> None:
        for i in range(0, len(keys), _BATCH):
            objects = [{"Key": self._name(k)} for k in keys[i:i + _BATCH]]
            res = self._call("delete", keys[i], "delete_objects", Delete={"Objects": objects, "Quiet": True})
            errors = res.get("Errors") or []
            if errors:
                raise StoreError(f"blob {self._key(errors[0]['Key'])!r}: cannot delete it in the {self.where}: "
                                 f"{errors[0].get('Code')}: {errors[0].get('Message')}")

    def check_writable(self) -> None:
        probe = f"probe-{secrets.token_hex(6)}"
        try:
            self.write(probe, b"")
            self.delete([probe])
        except (StoreError, BlobMissing) as err:
            raise StoreError(f"{self.where}: cannot write a blob there ({str(err).split(': ', 1)[-1]}); "
                             "the farm's processes write textures and gradients there") from None

    def close(self) -> None:
        self.client.close()
