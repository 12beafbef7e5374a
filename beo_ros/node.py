from beo_ros.ros.node import main

if __name__ == '__main__':
    main()
