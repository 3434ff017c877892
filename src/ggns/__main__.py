"""`python -m ggns <command>`: the command line (`ggns.cli`, its usage in `ggns.cli.USAGE`)."""
import os

# Large CPU tensors in transparent huge pages (PyTorch's own switch, read at its first allocation, so set
# before torch is imported): a paper-size training step then takes far fewer page faults (docs/speed.md)
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

from .cli import main  # noqa: E402

if __name__ == "__main__":
    main()
