"""colcon (ament_python) entry for area3d_semantics; pip users install everything from the root pyproject."""

if __name__ == "__main__":
    from setuptools import setup

    setup(
        name="area3d_semantics",
        version="0.1.0",
        packages=["area3d_semantics"],
        package_dir={"area3d_semantics": "."},
        package_data={"area3d_semantics": ["prompts/*.txt"]},
        data_files=[
            ("share/ament_index/resource_index/packages", ["resource/area3d_semantics"]),
            ("share/area3d_semantics", ["package.xml"]),
        ],
        install_requires=["setuptools"],
        zip_safe=True,
        entry_points={"console_scripts": ["semantics_node = area3d_semantics.node:main"]},
    )
