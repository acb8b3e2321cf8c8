"""colcon (ament_python) entry for sim_bridge; pip users install everything from the root pyproject."""

if __name__ == "__main__":
    from setuptools import setup

    setup(
        name="sim_bridge",
        version="0.1.0",
        packages=["sim_bridge"],
        package_dir={"sim_bridge": "."},
        package_data={"sim_bridge": ["scenes/*/*", "scanned/*"]},
        data_files=[
            ("share/ament_index/resource_index/packages", ["resource/sim_bridge"]),
            ("share/sim_bridge", ["package.xml"]),
        ],
        install_requires=["setuptools"],
        zip_safe=True,
        entry_points={"console_scripts": ["sim_bridge_node = sim_bridge.node:main"]},
    )
