"""What an open HDF5 split file keeps while a reader visits its trajectories (docs/streaming.md): resident
memory growth and time per trajectory of `SplitReader.info` over one file, with HDF5's default metadata cache
and capped ones, then a read of every 20th trajectory; and the cost of opening and closing a file.

    python scripts/probe_hdf5_metadata.py FILE.h5 [OTHER.h5]   # one process per setting
"""
import subprocess
import sys
import time


def rss_mb() -> float:
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 1e6


def case(path: str, cap: str) -> None:
    from ggns.data.schema import SplitReader

    reader = SplitReader(path, metadata_cache=None if cap == "default" else int(cap))
    start_rss, start = rss_mb(), time.perf_counter()
    for i in range(len(reader)):
        reader.info(i)
    per = (time.perf_counter() - start) / len(reader) * 1e3
    grown = rss_mb() - start_rss
    picks = range(0, len(reader), 20)
    start = time.perf_counter()
    for i in picks:
        reader[i]
    read = (time.perf_counter() - start) / len(picks) * 1e3
    print(f"cache {cap}: {len(reader)} trajectories, info {per:.2f} ms each, +{grown:.1f} MB resident; "
          f"a read {read:.2f} ms, +{rss_mb() - start_rss:.1f} MB after them")


def open_close(path: str) -> None:
    import h5py

    start = time.perf_counter()
    for _ in range(100):
        with h5py.File(path, "r") as f:
            f["trajectories"]["000005"]["mesh/positions"].shape
    print(f"open, one lookup, close: {(time.perf_counter() - start) * 10:.2f} ms")


if __name__ == "__main__":
    if sys.argv[1] == "--case":
        case(sys.argv[2], sys.argv[3]) if sys.argv[3] != "open" else open_close(sys.argv[2])
    else:
        for cap in ("default", str(2**22), str(2**20), str(2**18)):
            subprocess.run([sys.executable, __file__, "--case", sys.argv[1], cap], check=True)
        subprocess.run([sys.executable, __file__, "--case", sys.argv[-1], "open"], check=True)
