"""colcon (ament_python) entry for area3d_bringup; pip users install everything from the root pyproject."""

if __name__ == "__main__":
    from setuptools import setup

    setup(
        name="area3d_bringup",
        version="0.1.0",
        packages=["area3d_bringup"],
        package_dir={"area3d_bringup": "."},
        data_files=[
            ("share/ament_index/resource_index/packages", ["resource/area3d_bringup"]),
            ("share/area3d_bringup", ["package.xml"]),
            ("share/area3d_bringup/config", ["config/area3d.yaml", "config/robot_odometry.yaml"]),
            ("share/area3d_bringup/launch", ["launch/area3d.launch.py"]),
            ("share/area3d_bringup/rviz", ["rviz/area3d.rviz"]),
        ],
        install_requires=["setuptools"],
        zip_safe=True,
        entry_points={"console_scripts": ["area3d = area3d_bringup.cli:main"]},
    )
