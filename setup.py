from pathlib import Path

from setuptools import find_packages, setup

# The command line's file formats and previews (imported lazily; the core needs none): trimesh
# reads and writes PLY/OBJ, matplotlib (with its Pillow) draws PNG/GIF, tqdm shows progress,
# threadpoolctl gives BLAS one thread (--threads; one per `minretarget batch` worker).
# The .glb and .bvh writers need only NumPy.
CLI = ["trimesh>=4.0", "matplotlib>=3.6", "tqdm>=4.60", "threadpoolctl>=3.1"]
# `minretarget batch --ray`: the same job on a Ray cluster (tests/test_batch.py starts a
# local instance).
RAY = ["ray>=2.10"]

setup(
    name="minretarget",
    version="0.1.0",
    description="Correspondence-free online dense human motion retargeting on the CPU",
    long_description=Path(__file__).with_name("README.md").read_text(encoding="utf-8"),
    long_description_content_type="text/markdown",
    license="MIT",
    python_requires=">=3.10",
    # Only the runtime is installed: `training` (the torch reference) runs from the checkout
    # (`python -m training...` from the repository root), never from site-packages.
    packages=find_packages(include=["minretarget", "minretarget.*"]),
    # py.typed: the public API's type hints are for users' type checkers too (PEP 561).
    package_data={"minretarget": ["data/*.npz", "data/*.json", "data/*.sha256", "py.typed"]},
    install_requires=["numpy>=1.24", "numba>=0.59", "scipy>=1.10"],
    entry_points={"console_scripts": ["minretarget = minretarget.cli:main"]},
    extras_require={
        "cli": CLI,
        # torch is pinned: 2.13.0's CPU wheel is on the project's machines, and an unpinned
        # torch pulls a multi-GB CUDA build.
        "train": ["torch==2.13.0", "anny==0.6.2", "trimesh>=4.0", "tqdm>=4.60", "matplotlib>=3.6"],
        "ray": RAY,
        "test": ["pytest>=7", "hypothesis>=6"] + CLI + RAY,
        # benchmarks/speed.py: the engines minretarget is compared with, and BLAS thread
        # control (threadpoolctl, the library scikit-learn uses for the same job)
        "bench": ["torch==2.13.0", "onnxruntime>=1.17", "onnx>=1.15", "onnxscript>=0.2",
                  "threadpoolctl>=3.1"],
    },
)
