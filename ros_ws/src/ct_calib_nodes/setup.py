from glob import glob

from setuptools import find_packages, setup

package_name = "ct_calib_nodes"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["nodes/*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Metrology cell team",
    maintainer_email="metrology@example.com",
    description="Cone-beam CT geometry calibration (Ferrucci et al. 2020) as ROS 2 nodes",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "mcap_recorder = ct_calib_nodes.nodes.mcap_recorder:main",
            "ct_projection_sim = ct_calib_nodes.nodes.ct_projection_sim:main",
            "ct_sphere_detector = ct_calib_nodes.nodes.ct_sphere_detector:main",
            "ct_geometry_solver = ct_calib_nodes.nodes.ct_geometry_solver:main",
            "ct_error_motion = ct_calib_nodes.nodes.ct_error_motion:main",
            "ct_discrepancy_node = ct_calib_nodes.nodes.ct_discrepancy_node:main",
            "ct_demo = ct_calib_nodes.nodes.ct_demo:main",
            "ct_offline_solve = ct_calib_nodes.offline:main",
            "ct_discrepancy = ct_calib_nodes.discrepancy_cli:main",
            "ct_history = ct_calib_nodes.history_cli:main",
            "ct_archive_solve = ct_calib_nodes.archive:main",
        ],
    },
)
