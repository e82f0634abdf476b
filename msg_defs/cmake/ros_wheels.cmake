# Building an ament_cmake interface package against the ROS 2 pip wheels. Included right after
# project() by msg_defs/CMakeLists.txt, and as CMAKE_PROJECT_INCLUDE by tools/setup.sh --test for
# the vendored composition_interfaces (an unmodified upstream package). On a regular ROS 2
# installation (colcon) nothing here changes anything.

# `pip wheel` (scikit-build-core, SKBUILD set): the wheels' ament prefix is four levels above the
# rosidl_cmake Python package (the venv root, or pip's isolated build environment).
if(SKBUILD)
  find_package(Python3 REQUIRED COMPONENTS Interpreter)
  execute_process(
    COMMAND "${Python3_EXECUTABLE}" -c
      "import pathlib, rosidl_cmake; print(pathlib.Path(rosidl_cmake.__file__).resolve().parents[4])"
    OUTPUT_VARIABLE _ros_prefix OUTPUT_STRIP_TRAILING_WHITESPACE COMMAND_ERROR_IS_FATAL ANY)
  message(STATUS "${PROJECT_NAME}: ROS 2 wheels prefix ${_ros_prefix}")
  list(PREPEND CMAKE_PREFIX_PATH "${_ros_prefix}")
  set(ENV{AMENT_PREFIX_PATH} "${_ros_prefix}")
  # Lay the package out like the ROS wheels do, so lib/pythonX.Y/site-packages lands in the venv.
  set(PYTHON_INSTALL_DIR "lib/python${Python3_VERSION_MAJOR}.${Python3_VERSION_MINOR}/site-packages")
endif()

# The pip wheels of ROS 2 export imported targets (*__rosidl_generator_py and others) whose include
# directories point into the container they were built in (/opt/python/...). CMake's generate step
# fails on such missing paths, so once the package's CMakeLists.txt has run (the targets exist only
# after rosidl_generate_interfaces), drop the entries that do not exist here.
function(_ros_wheels_drop_missing_include_dirs)
  get_property(_imported_targets DIRECTORY PROPERTY IMPORTED_TARGETS)
  foreach(_target IN LISTS _imported_targets)
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_kept "")
    foreach(_dir IN LISTS _dirs)
      if(_dir MATCHES "^\\$<" OR EXISTS "${_dir}")
        list(APPEND _kept "${_dir}")
      endif()
    endforeach()
    if(NOT "${_kept}" STREQUAL "${_dirs}")
      set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
    endif()
  endforeach()
endfunction()
cmake_language(DEFER DIRECTORY "${CMAKE_CURRENT_SOURCE_DIR}" CALL _ros_wheels_drop_missing_include_dirs)
