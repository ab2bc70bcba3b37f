"""The object-storage I/O layer, chosen by measurement: obstore (what bigT uses) against
s3fs (fsspec) putting and getting the objects of tile rows on an S3-compatible server on
loopback (moto, ``bigT.testing.S3Server``, 127.0.0.1 only).

Each layer puts then gets ``--count`` objects of each size (a small row's array, a
dense row's), one at a time and ``--parallel`` in flight, best of ``--repeats``, in the
same process against the same server. s3fs is not a bigT dependency: run this with an
interpreter that has it (``pip install s3fs``); without it only obstore is timed.

    python benchmarks/bench_object_io.py
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _obstore_ops(bucket: str):
    import obstore
    from obstore.store import from_url

    store = from_url(f"s3://{bucket}", client_options={"allow_http": True})

    def put(key, data):
        obstore.put(store, key, data, use_multipart=False)

    def get(key):
        return bytes(obstore.get(store, key).bytes())
    return put, get


def _s3fs_ops(bucket: str):
    import s3fs

    fs = s3fs.S3FileSystem(endpoint_url=os.environ["AWS_ENDPOINT_URL"])

    def put(key, data):
        fs.pipe_file(f"{bucket}/{key}", data)

    def get(key):
        return fs.cat_file(f"{bucket}/{key}")
    return put, get


def _time(fn, items, parallel: int) -> float:
    t0 = time.perf_counter()
    if parallel > 1:
        with ThreadPoolExecutor(parallel) as pool:
            list(pool.map(fn, items))
    else:
        for x in items:
            fn(x)
    return time.perf_counter() - t0


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--count", type=int, default=100)
    p.add_argument("--sizes", default="65536,4194304")
    p.add_argument("--parallel", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--endpoint", default=None,
                   help="a running S3-compatible server on 127.0.0.1 (default: start moto)")
    args = p.parse_args(argv)
    layers = {"obstore": _obstore_ops}
    try:
        import s3fs  # noqa: F401
        layers["s3fs"] = _s3fs_ops
    except ImportError:
        print("s3fs not installed: obstore only", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        if args.endpoint is None:
            from bigT.testing import S3Server

            with S3Server(Path(tmp)) as s3:
                os.environ.update(s3.env)
                rows = _measure(layers, s3.bucket, args)
        else:
            import urllib.request

            os.environ.update(AWS_ENDPOINT_URL=args.endpoint, AWS_ACCESS_KEY_ID="testing",
                              AWS_SECRET_ACCESS_KEY="testing", AWS_REGION="us-east-1")
            urllib.request.urlopen(urllib.request.Request(f"{args.endpoint}/bench",
                                                          method="PUT")).close()
            rows = _measure(layers, "bench", args)
    print(json.dumps(rows, indent=1))


def _measure(layers: dict, bucket: str, args) -> list[dict]:
    rows = []
    for size in map(int, args.sizes.split(",")):
        data = os.urandom(size)
        for name, make in layers.items():
            put, get = make(bucket)
            keys = [f"{name}/{size}/{i}" for i in range(args.count)]
            for parallel in (1, args.parallel):
                best_put = min(_time(lambda k: put(k, data), keys, parallel)
                               for _ in range(args.repeats))
                best_get = min(_time(get, keys, parallel) for _ in range(args.repeats))
                rows.append({"layer": name, "bytes": size, "in flight": parallel,
                             "put ms": round(1e3 * best_put / args.count, 2),
                             "get ms": round(1e3 * best_get / args.count, 2),
                             "get MB/s": round(size * args.count / best_get / 1e6, 1)})
                print(json.dumps(rows[-1]), flush=True)
    return rows


if __name__ == "__main__":
    main()
