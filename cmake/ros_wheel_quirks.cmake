# Include-directory fixes an interface package needs when it is built against the ros-jazzy-*
# wheels from PyPI (make venv), harmless against /opt/ros/jazzy (colcon). Included by this
# package's CMakeLists.txt and by interfaces/tf2_msgs/CMakeLists.txt; call both functions at
# the end of the CMakeLists.txt, after ament_package().

# The imported targets of the ROS wheels from PyPI carry include directories of the machine
# they were built on (/opt/python/cp311-cp311/...); CMake's generate step then fails with
# "includes non-existent path". Drop every include directory that does not exist here
# (generator expressions are kept as they are).
function(drop_missing_imported_include_directories)
  get_property(_imported_targets DIRECTORY PROPERTY IMPORTED_TARGETS)
  foreach(_target IN LISTS _imported_targets)
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_kept "")
    foreach(_dir IN LISTS _dirs)
      if(_dir MATCHES "\\$<" OR EXISTS "${_dir}")
        list(APPEND _kept "${_dir}")
      endif()
    endforeach()
    if(NOT "${_kept}" STREQUAL "${_dirs}")
      set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
    endif()
  endforeach()
endfunction()

# A virtual environment inside the source tree (make venv's .venv, used by colcon too) puts
# numpy's include directory, which rosidl_generator_py exports, under the source directory,
# and CMake refuses to export such a path unless it lies under the install prefix: keep it
# for the build tree only.
function(keep_source_include_directories_in_build_tree)
  get_property(_own_targets DIRECTORY PROPERTY BUILDSYSTEM_TARGETS)
  foreach(_target IN LISTS _own_targets)
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT _dirs)
      continue()
    endif()
    set(_kept "")
    foreach(_dir IN LISTS _dirs)
      cmake_path(IS_PREFIX CMAKE_CURRENT_SOURCE_DIR "${_dir}" NORMALIZE _in_source)
      cmake_path(IS_PREFIX CMAKE_INSTALL_PREFIX "${_dir}" NORMALIZE _in_prefix)
      if(NOT _dir MATCHES "\\$<" AND _in_source AND NOT _in_prefix)
        set(_dir "$<BUILD_INTERFACE:${_dir}>")
      endif()
      list(APPEND _kept "${_dir}")
    endforeach()
    set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_kept}")
  endforeach()
endfunction()
