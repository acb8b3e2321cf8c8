# Included by tools/build_interfaces.py as CMAKE_PROJECT_INCLUDE (not by colcon: a ROS 2 install
# needs none of this).
#
# The ROS 2 message wheels export `<pkg>::<pkg>__rosidl_generator_py` targets whose include
# directories are those of the machine that built the wheels (/opt/python/...). CMake refuses an
# imported target with a missing include directory, so once the project's directory is processed,
# every such target gets this machine's Python and NumPy include directories instead
# (AREA3D_PYTHON_INCLUDE_DIRS, passed by the build script).
if(CMAKE_VERSION VERSION_LESS 3.21)  # the IMPORTED_TARGETS directory property
  message(FATAL_ERROR "CMake ${CMAKE_VERSION} is too old: 3.21 or newer is needed")
endif()

function(area3d_use_local_python_includes)
  get_property(targets DIRECTORY "${CMAKE_SOURCE_DIR}" PROPERTY IMPORTED_TARGETS)
  foreach(target IN LISTS targets)
    if(NOT target MATCHES "__rosidl_generator_py$")
      continue()
    endif()
    get_target_property(dirs ${target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT dirs)
      continue()
    endif()
    set(missing FALSE)
    foreach(dir IN LISTS dirs)
      if(NOT EXISTS "${dir}")
        set(missing TRUE)
      endif()
    endforeach()
    if(missing)
      set_target_properties(${target} PROPERTIES
        INTERFACE_INCLUDE_DIRECTORIES "${AREA3D_PYTHON_INCLUDE_DIRS}")
    endif()
  endforeach()
endfunction()

if(NOT AREA3D_PYTHON_INCLUDE_DIRS)
  message(FATAL_ERROR "AREA3D_PYTHON_INCLUDE_DIRS is not set: run tools/build_interfaces.py")
endif()
cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL area3d_use_local_python_includes)
