"""colcon (ament_python) entry for area3d_bench; pip users install everything from the root pyproject."""

if __name__ == "__main__":
    from setuptools import setup

    setup(
        name="area3d_bench",
        version="0.1.0",
        packages=["area3d_bench"],
        package_dir={"area3d_bench": "."},
        data_files=[
            ("share/ament_index/resource_index/packages", ["resource/area3d_bench"]),
            ("share/area3d_bench", ["package.xml"]),
        ],
        install_requires=["setuptools"],
        zip_safe=True,
        # `area3d bench`: the area3d command adds the groups of this entry point group
        entry_points={"console_scripts": [], "area3d.cli": ["bench = area3d_bench.cli:app"]},
    )
