from setuptools import find_packages, setup

package_name = "picms_nodes"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Metrology cell team",
    maintainer_email="metrology@example.com",
    description="Pixel Probe / PiCMS cell (skeleton; nodes arrive with their issues)",
    license="Apache-2.0",
    entry_points={"console_scripts": []},
)
