from setuptools import find_packages, setup

package_name = "picms_nodes"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", ["config/picms_cell.yaml", "config/part_program_targets.yaml",
                                                 "config/part_program_flange.yaml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Metrology cell team",
    maintainer_email="metrology@example.com",
    description="Pixel Probe / PiCMS cell: camera, stage and tracker simulators, Pixel Probe calibration",
    license="Apache-2.0",
    entry_points={"console_scripts": [
        "picms_stage_sim = picms_nodes.nodes.picms_stage_sim:main",
        "picms_camera_sim = picms_nodes.nodes.picms_camera_sim:main",
        "picms_tracker_sim = picms_nodes.nodes.picms_tracker_sim:main",
        "picms_calibration = picms_nodes.nodes.picms_calibration:main",
        "picms_calibrate_offline = picms_nodes.offline:main",
        "picms_demo = picms_nodes.nodes.picms_demo:main",
        "picms_measure_offline = picms_nodes.measure_offline:main",
        "picms_discrepancy = picms_nodes.discrepancy_cli:main",
        "picms_measure_demo = picms_nodes.measure_demo:main",
        "picms_targeting = picms_nodes.nodes.picms_targeting:main",
        "picms_measurement = picms_nodes.nodes.picms_measurement:main",
    ]},
)
