# Included after project() of an interface package built against the ROS 2 Jazzy PyPI wheels
# (generate.py passes it as CMAKE_PROJECT_INCLUDE, with STARLETH_PYTHON_INCLUDE and
# STARLETH_NUMPY_INCLUDE).
#
# The message wheels' exported targets (share/<pkg>/cmake/export_<pkg>__rosidl_generator_py
# Export.cmake) name the include directories of the machine that built the wheels
# (/opt/python/cp311-cp311/include/python3.11 and its numpy's include directory). CMake
# refuses an imported target whose include directory does not exist. Rather than rewrite the
# wheels' files, the imported targets' properties are corrected here, in this build only, at
# the end of configuring (once every find_package has imported its targets): a missing
# Python include directory becomes this interpreter's, a missing numpy one this numpy's.
cmake_minimum_required(VERSION 3.19)   # cmake_language(DEFER)

function(starleth_point_wheel_include_dirs_here)
  get_directory_property(targets IMPORTED_TARGETS)
  foreach(target IN LISTS targets)
    get_target_property(dirs ${target} INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT dirs)
      continue()
    endif()
    set(fixed "")
    foreach(dir IN LISTS dirs)
      if(NOT EXISTS "${dir}" AND dir MATCHES "/numpy/(_core/)?include$")
        set(dir "${STARLETH_NUMPY_INCLUDE}")
      elseif(NOT EXISTS "${dir}" AND dir MATCHES "/include/python3\\.[0-9]+$")
        set(dir "${STARLETH_PYTHON_INCLUDE}")
      endif()
      list(APPEND fixed "${dir}")
    endforeach()
    if(NOT fixed STREQUAL dirs)
      set_target_properties(${target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${fixed}")
    endif()
  endforeach()
endfunction()

cmake_language(DEFER CALL starleth_point_wheel_include_dirs_here)
