"""Run the stereorepro CLI from the snapshot in ./code (commit d798c7b), not the editable checkout."""

import sys
from pathlib import Path

sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in type(f).__module__.lower()]
sys.path.insert(0, str(Path(__file__).resolve().parent / "code"))
import stereorepro  # noqa: E402

assert stereorepro.__file__.startswith(str(Path(__file__).resolve().parent)), stereorepro.__file__
from stereorepro.cli import main  # noqa: E402

sys.exit(main(sys.argv[1:]))
