"""Record the SHA-256 of the shipped default weights, which ``load_weights`` checks.

    python -m minretarget.checksum [WEIGHTS]

checks that the file (default: ``minretarget/data/default_weights.npz``) loads as weights,
then writes ``<name>.sha256`` beside it (``sha256sum`` format). Run it after replacing the
default weights, and ship both files.
"""
import argparse
import sys

from . import weights


def main(argv=None):
    parser = argparse.ArgumentParser(prog="python -m minretarget.checksum",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("path", nargs="?", default=None,
                        help=f"weights .npz (default {weights.DEFAULT_WEIGHTS})")
    args = parser.parse_args(argv)
    try:
        digest = weights.record_checksum(args.path)
    except (ValueError, OSError) as error:
        print(f"minretarget.checksum: error: {error}", file=sys.stderr)
        return 1
    path = weights.DEFAULT_WEIGHTS if args.path is None else args.path
    print(f"{digest}  recorded in {weights.checksum_path(path)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
