"""msfnet.calib"""
