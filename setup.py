"""Ship the data folders (models/, tuning/, coach/) inside the package as pidlab/_data/.

Everything else is in pyproject.toml. pidlab.data finds the source tree's folders first, so an
editable install reads (and the tuner writes) the checkout's files; a regular install reads the
copies made here.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

DATA_FOLDERS = ("models", "tuning", "coach")


class BuildWithData(build_py):
    """build_py, plus a copy of the data folders' TOML files into the built package."""

    def run(self) -> None:
        super().run()
        root = Path(__file__).resolve().parent
        for name in DATA_FOLDERS:
            target = Path(self.build_lib) / "pidlab" / "_data" / name
            target.mkdir(parents=True, exist_ok=True)
            for path in sorted((root / name).glob("*.toml")):
                shutil.copy2(path, target / path.name)


setup(cmdclass={"build_py": BuildWithData})
