"""colcon (ament_python) entry for area3d_reconstruction; pip users install everything from the root pyproject."""

if __name__ == "__main__":
    from setuptools import setup

    setup(
        name="area3d_reconstruction",
        version="0.1.0",
        packages=["area3d_reconstruction"],
        package_dir={"area3d_reconstruction": "."},
        data_files=[
            ("share/ament_index/resource_index/packages", ["resource/area3d_reconstruction"]),
            ("share/area3d_reconstruction", ["package.xml"]),
        ],
        install_requires=["setuptools"],
        zip_safe=True,
        entry_points={"console_scripts": ["reconstruction_node = area3d_reconstruction.node:main"]},
    )
