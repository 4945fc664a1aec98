import glob
import os

from setuptools import find_packages, setup

with open(os.path.join("sb3_dipper", "version.txt")) as file_handler:
    __version__ = file_handler.read().strip()

with open("README.md", encoding="utf-8") as file_handler:
    long_description = file_handler.read()

setup(
    name="sb3-dipper",
    version=__version__,
    description="DIPPER (direct preference optimization for hierarchical RL) and its baselines for Stable-Baselines3",
    long_description=long_description,
    long_description_content_type="text/markdown",
    packages=find_packages(include=["sb3_dipper", "sb3_dipper.*"]),
    package_data={"sb3_dipper": ["py.typed", "version.txt"]},
    # The zoo's hyperparameter files, found by sb3_dipper.zoo.hyperparams_dir() in an installed package.
    data_files=[
        ("share/sb3-dipper/hyperparams", sorted(glob.glob("hyperparams/*.yml"))),
        ("share/sb3-dipper/hyperparams/paper", sorted(glob.glob("hyperparams/paper/*.yml"))),
    ],
    python_requires=">=3.10",
    install_requires=[
        # The Makefile installs torch first (TORCH_SPEC: 2.13.0, the CPU build the development and CI machines hold in
        # pip's local wheel folder), so there this range is already met and pulls no other build.
        "torch>=2.8,<3",
        "stable-baselines3>=2.9.2,<3",
        "sb3-contrib>=2.9.2,<3",
        "gymnasium>=1.2,<2",
        "gymnasium-robotics>=1.4.2,<1.5",
        # mujoco 3.12 and later break gymnasium-robotics 1.4.2 (Fetch and Kitchen joint-type assertion).
        "mujoco>=3.3,<3.12",
        "numpy>=1.24",
        "tqdm",
        "rich",
    ],
    extras_require={
        # rl-zoo3's enjoy imports requests without declaring it; its -tb (SB3's tensorboard_log) needs tensorboard.
        "zoo": ["rl-zoo3[plots]>=2.9.2,<3", "requests", "pyyaml", "moviepy>=1.0", "tensorboard>=2.9"],
        "plots": ["matplotlib>=3.7", "pandas>=2.2", "rliable>=1.2"],
        # Reading Minari dataset directories as demonstrations.
        "minari": ["minari[hdf5]>=0.5"],
        # zoo_scripts/benchmark.py --ray-address: learning runs as tasks on a Ray cluster.
        "cluster": ["ray>=2.9"],
        # sb3-dipper-label: the labelling page (Flask) and its pictures of pairs (matplotlib).
        "label": ["flask>=3", "matplotlib>=3.7"],
        # `make docs`: the Sphinx site (the SB3 family's theme; myst-parser includes the Markdown changelog; MathJax from
        # a package, so that math renders without a network) and flask, which autodoc needs to import the labelling page;
        # `make screenshots`: markdown renders the README as HTML.
        "docs": [
            "sphinx>=7,<10",
            "sphinx-rtd-theme>=2,<4",
            "myst-parser>=2,<6",
            "sphinx-mathjax-offline>=0.0.2",
            "flask>=3",
            "markdown>=3.4",
        ],
        "tests": [
            "pytest>=8",
            "pytest-timeout",
            "pytest-xdist",
            "ruff",
            "mypy",
            "types-PyYAML",
            "minari[hdf5]>=0.5",
            "ray>=2.9",
            # tests/test_sb3_contracts.py trains with tensorboard_log=.
            "tensorboard>=2.9",
            # tests/test_labelling.py: the labelling page, driven in the system's headless Chromium.
            "flask>=3",
            "selenium>=4.20",
            # tests/tools/test_docs.py builds a page with the docs' math extensions.
            "sphinx>=7,<10",
            "sphinx-mathjax-offline>=0.0.2",
        ],
    },
    entry_points={
        "console_scripts": [
            "sb3-dipper-demos = sb3_dipper.envs.demos:main",
            "sb3-dipper-zoo = sb3_dipper.zoo:main",
            "sb3-dipper-label = sb3_dipper.labelling.app:main",
        ]
    },
    license="MIT",
    classifiers=[
        "Programming Language :: Python :: 3",
        "License :: OSI Approved :: MIT License",
    ],
)
